//! A simulation run and its dataset folder:
//! `scans/NNNNNN.pcd` (binary PCD with view directions and per-point time),
//! `poses_gt.txt` (TUM, at each scan stamp), `poses_imu_gt.txt` (TUM, at each IMU
//! stamp), `imu.csv` and `meta.toml`.

use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::imu::{ImuParams, gravity_in_map, imu_samples};
use super::lidar::{LidarParams, sweep};
use super::noise::stream;
use super::presets::{Preset, Site, build_site};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::{ImuSample, format_imu_csv};
use kfmap_geometry::io::{
    CloudFormat, IoError, PcdData, Trajectory as PoseList, encode_cloud, format_tum, write_atomic,
};
use kfmap_geometry::options::{InvalidOption, ensure};

/// Everything that defines a simulation run; saved as `meta.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SimConfig {
    /// The site.
    pub preset: Preset,
    /// Simulated duration, seconds.
    pub seconds: f64,
    /// Seed of the clutter placement and of all noise.
    pub seed: u64,
    /// World (gravity) frame tilt against the map frame, `[roll, pitch]` in degrees.
    pub tilt_deg: [f64; 2],
    /// Cruise speed of the drive, m/s, instead of the preset's (courtyard and corridor 2,
    /// campus 5, street 10); the start from rest and the +-20 % swing stay.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cruise_speed: Option<f64>,
    /// LiDAR model.
    pub lidar: LidarParams,
    /// IMU model.
    pub imu: ImuParams,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            preset: Preset::Courtyard,
            seconds: 10.0,
            seed: 1,
            tilt_deg: [0.0, 0.0],
            cruise_speed: None,
            lidar: LidarParams::default(),
            imu: ImuParams::default(),
        }
    }
}

impl SimConfig {
    /// The same run with every noise source off (range noise, dropouts, IMU noise and
    /// biases).
    pub fn without_noise(mut self) -> Self {
        self.lidar.range_noise_sigma = 0.0;
        self.lidar.dropout = 0.0;
        self.imu = self.imu.noiseless();
        self
    }

    /// Checks every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            self.seconds.is_finite() && self.seconds > 0.0 && self.seconds <= 36_000.0,
            "seconds",
            self.seconds,
            "more than 0 and at most 36000 s",
        )?;
        for (name, angle) in [
            ("tilt roll", self.tilt_deg[0]),
            ("tilt pitch", self.tilt_deg[1]),
        ] {
            ensure(
                angle.is_finite() && angle.abs() <= 45.0,
                name,
                angle,
                "-45 to 45 degrees",
            )?;
        }
        if let Some(speed) = self.cruise_speed {
            ensure(
                speed.is_finite() && (0.1..=40.0).contains(&speed),
                "speed",
                speed,
                "0.1 to 40 m/s",
            )?;
        }
        self.lidar.validate()?;
        self.imu.validate()
    }

    /// Gravity in the map frame, m/s^2.
    pub fn gravity_map(&self) -> Vector3<f64> {
        gravity_in_map(self.tilt_deg[0].to_radians(), self.tilt_deg[1].to_radians())
    }

    /// Number of sweeps that fit in `seconds`.
    pub fn scan_count(&self) -> usize {
        (self.seconds * self.lidar.rate_hz).floor().max(1.0) as usize
    }
}

/// A simulation ready to produce scans and IMU data.
pub struct Simulation {
    config: SimConfig,
    site: Site,
}

/// One simulated sweep.
#[derive(Debug, Clone)]
pub struct SimScan {
    /// Sweep start, seconds.
    pub stamp: f64,
    /// Ground-truth `T_map_sensor` at the stamp.
    pub pose: Pose,
    /// The points (sensor frame), view directions and per-point times.
    pub cloud: PointCloud,
}

impl Simulation {
    /// Builds the site of a validated configuration.
    pub fn new(config: SimConfig) -> Result<Self, InvalidOption> {
        config.validate()?;
        let mut site = build_site(config.preset, config.seed);
        if let Some(cruise) = config.cruise_speed {
            site.trajectory = site.trajectory.with_cruise(cruise);
        }
        Ok(Self { config, site })
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The site (scene and trajectory).
    pub fn site(&self) -> &Site {
        &self.site
    }

    /// Ground-truth `T_map_sensor` at the start of sweep `index` (no ray casting).
    pub fn scan_pose(&self, index: usize) -> Pose {
        self.site
            .trajectory
            .pose(index as f64 / self.config.lidar.rate_hz)
    }

    /// Sweep number `index` (each has its own noise stream: any order, same bytes).
    pub fn scan(&self, index: usize) -> SimScan {
        let stamp = index as f64 / self.config.lidar.rate_hz;
        let mut rng = stream(self.config.seed, index as u64);
        let cloud = sweep(
            &self.site.scene,
            &self.site.trajectory,
            &self.config.lidar,
            stamp,
            &mut rng,
        );
        SimScan {
            stamp,
            pose: self.site.trajectory.pose(stamp),
            cloud,
        }
    }

    /// IMU samples over the whole run.
    pub fn imu(&self) -> Vec<ImuSample> {
        imu_samples(
            &self.site.trajectory,
            &self.config.imu,
            &self.config.gravity_map(),
            0.0,
            self.config.seconds,
            self.config.seed,
        )
    }
}

/// Why a dataset could not be written.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A parameter is out of range.
    #[error(transparent)]
    Invalid(#[from] InvalidOption),
    /// The output folder exists and is not empty.
    #[error("{}: output folder is not empty; choose another or pass --force", .0.display())]
    NotEmpty(PathBuf),
    /// Writing failed.
    #[error(transparent)]
    Io(#[from] IoError),
}

/// What a finished run wrote.
#[derive(Debug, Clone, Serialize)]
pub struct SimSummary {
    /// Scans written.
    pub scans: usize,
    /// Points in all scans.
    pub points: usize,
    /// IMU samples written.
    pub imu_samples: usize,
    /// Metres driven.
    pub distance_m: f64,
    /// Scene primitives.
    pub shapes: usize,
}

/// `meta.toml`: the configuration plus facts a consumer checks against.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub struct SimMeta {
    /// The run's configuration.
    pub config: SimConfig,
    /// Gravity in the map frame, m/s^2 (what gravity alignment should find).
    pub gravity_map: [f64; 3],
    /// Scans written.
    pub scans: usize,
    /// Length of one lap of the path, metres.
    pub lap_length_m: f64,
    /// kfmap version that wrote the dataset.
    pub kfmap_version: String,
}

fn poses_at(sim: &Simulation, stamps: impl Iterator<Item = f64>) -> PoseList {
    let stamps: Vec<f64> = stamps.collect();
    let poses = stamps
        .iter()
        .map(|&t| sim.site.trajectory.pose(t))
        .collect();
    PoseList {
        stamps: Some(stamps),
        poses,
    }
}

/// Runs `config` and writes its dataset into `out` (created if missing; must be empty
/// unless `force`). `progress(done, total)` is called after each scan.
pub fn write_dataset(
    config: SimConfig,
    out: &Path,
    force: bool,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<SimSummary, SimError> {
    let sim = Simulation::new(config)?;
    let not_empty = std::fs::read_dir(out)
        .map(|mut d| d.next().is_some())
        .unwrap_or(false);
    if not_empty && !force {
        return Err(SimError::NotEmpty(out.to_path_buf()));
    }
    let scans_dir = out.join("scans");
    std::fs::create_dir_all(&scans_dir).map_err(|e| IoError::os(&scans_dir, e))?;
    // With --force, scans left by an earlier, longer run would pose as part of this one.
    for entry in std::fs::read_dir(&scans_dir)
        .map_err(|e| IoError::os(&scans_dir, e))?
        .flatten()
    {
        if entry.path().extension().is_some_and(|e| e == "pcd") {
            std::fs::remove_file(entry.path()).map_err(|e| IoError::os(entry.path(), e))?;
        }
    }

    let total = sim.config.scan_count();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let points: Vec<usize> = (0..total)
        .into_par_iter()
        .map(|i| {
            let scan = sim.scan(i);
            let path = scans_dir.join(format!("{i:06}.pcd"));
            write_atomic(
                &path,
                &encode_cloud(&scan.cloud, CloudFormat::Pcd(PcdData::Binary)),
            )?;
            progress(
                done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
                total,
            );
            Ok(scan.cloud.len())
        })
        .collect::<Result<_, IoError>>()?;

    let rate = sim.config.lidar.rate_hz;
    write_atomic(
        &out.join("poses_gt.txt"),
        format_tum(&poses_at(&sim, (0..total).map(|i| i as f64 / rate))).as_bytes(),
    )?;
    let imu = sim.imu();
    write_atomic(
        &out.join("poses_imu_gt.txt"),
        format_tum(&poses_at(&sim, imu.iter().map(|s| s.t))).as_bytes(),
    )?;
    write_atomic(&out.join("imu.csv"), format_imu_csv(&imu).as_bytes())?;
    let meta = SimMeta {
        gravity_map: sim.config.gravity_map().into(),
        scans: total,
        lap_length_m: sim.site.trajectory.spline().total_length(),
        kfmap_version: env!("CARGO_PKG_VERSION").to_string(),
        config: sim.config.clone(),
    };
    let meta_text = toml::to_string(&meta).expect("meta serializes");
    write_atomic(&out.join("meta.toml"), meta_text.as_bytes())?;
    let start = sim.site.trajectory.pose(0.0).translation.vector;
    let distance = (1..=100)
        .map(|k| sim.config.seconds * k as f64 / 100.0)
        .scan(start, |prev, t| {
            let p = sim.site.trajectory.pose(t).translation.vector;
            let step = (p - *prev).norm();
            *prev = p;
            Some(step)
        })
        .sum();
    Ok(SimSummary {
        scans: total,
        points: points.iter().sum(),
        imu_samples: imu.len(),
        distance_m: distance,
        shapes: sim.site.scene.shape_count(),
    })
}
