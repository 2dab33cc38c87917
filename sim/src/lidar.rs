//! A spinning multi-beam LiDAR: beams at fixed elevations sweep the azimuth once per
//! period while the vehicle moves; every return is cast exactly against the scene.

use nalgebra::Vector3;
use rand::Rng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};

use super::noise::gaussian;
use super::scene::Scene;
use super::shapes::Ray;
use super::trajectory::Trajectory;
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::to_point;
use kfmap_geometry::options::{InvalidOption, ensure};

/// LiDAR model parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct LidarParams {
    /// Number of beams: 16, 32, 64 or 128 (VLP-16, HDL-32E, HDL-64E, OS-128 layouts).
    pub beams: u32,
    /// Sweeps per second, Hz.
    pub rate_hz: f64,
    /// Azimuth step between firings, degrees.
    pub horizontal_resolution_deg: f64,
    /// Returns closer than this are discarded, metres.
    pub min_range: f64,
    /// Returns farther than this are discarded, metres.
    pub max_range: f64,
    /// Gaussian range noise, standard deviation in metres (0 = none).
    pub range_noise_sigma: f64,
    /// Probability that a return is dropped (0 = none).
    pub dropout: f64,
    /// Points in the sensor frame at the sweep start, without per-point times (true), or
    /// at their own firing time (false, "raw": motion distortion left in, per-point times
    /// tell when).
    pub deskew: bool,
}

impl Default for LidarParams {
    fn default() -> Self {
        Self {
            beams: 64,
            rate_hz: 10.0,
            horizontal_resolution_deg: 0.2,
            min_range: 0.5,
            max_range: 120.0,
            range_noise_sigma: 0.01,
            dropout: 0.02,
            deskew: true,
        }
    }
}

impl LidarParams {
    /// Elevation of every beam, radians, lowest first.
    pub fn elevations(&self) -> Vec<f64> {
        let (low, high) = match self.beams {
            16 => (-15.0, 15.0),
            32 => (-30.67, 10.67),
            64 => (-24.9, 2.0),
            _ => (-22.5, 22.5),
        };
        let n = self.beams as usize;
        (0..n)
            .map(|i| (low + (high - low) * i as f64 / (n - 1) as f64).to_radians())
            .collect()
    }

    /// Firings per sweep.
    pub fn columns(&self) -> usize {
        (360.0 / self.horizontal_resolution_deg).round() as usize
    }

    /// Checks every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            [16, 32, 64, 128].contains(&self.beams),
            "beams",
            self.beams,
            "16, 32, 64 or 128",
        )?;
        ensure(
            self.rate_hz.is_finite() && (1.0..=50.0).contains(&self.rate_hz),
            "rate-hz",
            self.rate_hz,
            "1 to 50 Hz",
        )?;
        let res = self.horizontal_resolution_deg;
        ensure(
            res.is_finite() && (0.01..=10.0).contains(&res),
            "horizontal-resolution-deg",
            res,
            "0.01 to 10 degrees",
        )?;
        ensure(
            self.min_range.is_finite() && self.min_range >= 0.0,
            "min-range",
            self.min_range,
            "a finite distance >= 0 m",
        )?;
        let max_ok = self.max_range.is_finite() && self.max_range > self.min_range;
        ensure(
            max_ok,
            "max-range",
            self.max_range,
            "a finite distance above min-range",
        )?;
        let sigma = self.range_noise_sigma;
        ensure(
            sigma.is_finite() && (0.0..=1.0).contains(&sigma),
            "range-noise-sigma",
            sigma,
            "0 to 1 m",
        )?;
        ensure(
            (0.0..1.0).contains(&self.dropout),
            "dropout",
            self.dropout,
            "a probability in [0, 1)",
        )
    }
}

/// One sweep starting at `t0` seconds: points with view directions (unit vectors toward
/// the sensor at firing time) and per-point times (seconds after `t0`).
pub fn sweep(
    scene: &Scene,
    trajectory: &Trajectory,
    params: &LidarParams,
    t0: f64,
    rng: &mut StdRng,
) -> PointCloud {
    let elevations: Vec<(f64, f64)> = params.elevations().iter().map(|e| e.sin_cos()).collect();
    let columns = params.columns();
    let period = 1.0 / params.rate_hz;
    let start_inverse = trajectory.pose(t0).inverse();
    let mut cloud = PointCloud {
        points: Vec::with_capacity(columns * elevations.len()),
        view_dirs: Some(Vec::with_capacity(columns * elevations.len())),
        intensity: None,
        time: Some(Vec::with_capacity(columns * elevations.len())),
    };
    for col in 0..columns {
        let dt = period * col as f64 / columns as f64;
        let pose = trajectory.pose(t0 + dt);
        let (sin_az, cos_az) = (std::f64::consts::TAU * col as f64 / columns as f64).sin_cos();
        // Sensor-at-firing to output frame: identity when raw, else T_start^-1 T_fire.
        let to_output = if params.deskew {
            start_inverse * pose
        } else {
            Default::default()
        };
        for &(sin_el, cos_el) in &elevations {
            let dir = Vector3::new(cos_el * cos_az, cos_el * sin_az, sin_el);
            let ray = Ray {
                origin: pose.translation.vector,
                dir: pose.rotation * dir,
            };
            let Some(hit) = scene.cast(&ray, params.max_range) else {
                continue;
            };
            // Draw both numbers for every hit so the stream does not depend on outcomes.
            let drop: f64 = rng.random();
            let range = hit + params.range_noise_sigma * gaussian(rng);
            if drop < params.dropout || range < params.min_range || range > params.max_range {
                continue;
            }
            let point = to_output * nalgebra::Point3::from(dir * range);
            let view = to_output.rotation * -dir;
            cloud.points.push(to_point(&point.coords));
            cloud
                .view_dirs
                .as_mut()
                .expect("set above")
                .push(to_point(&view));
            cloud.time.as_mut().expect("set above").push(dt as f32);
        }
    }
    if params.deskew {
        // Deskewed points all sit in the sweep-start frame: per-point times would tell
        // readers (kfmap's odometry) to deskew them a second time.
        cloud.time = None;
    }
    cloud
}
