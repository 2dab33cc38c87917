//! A 6-axis IMU on the body frame: accelerometer = specific force `R^T (a - g)` with
//! gravity along -Z of a world frame that may be tilted against the map frame, and
//! gyroscope = body angular velocity; each with a constant bias and white noise.

use nalgebra::{Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::noise::{gaussian, stream};
use super::trajectory::Trajectory;
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::options::{InvalidOption, ensure};

/// Standard gravity magnitude, m/s^2.
pub const GRAVITY: f64 = 9.81;

/// IMU model parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImuParams {
    /// Samples per second, Hz (100 to 400).
    pub rate_hz: f64,
    /// Accelerometer white noise, standard deviation per sample, m/s^2.
    pub acc_noise: f64,
    /// Gyroscope white noise, standard deviation per sample, rad/s.
    pub gyro_noise: f64,
    /// Magnitude of the constant accelerometer bias, m/s^2 (direction from the seed).
    pub acc_bias: f64,
    /// Magnitude of the constant gyroscope bias, rad/s (direction from the seed).
    pub gyro_bias: f64,
}

impl Default for ImuParams {
    fn default() -> Self {
        Self {
            rate_hz: 200.0,
            acc_noise: 0.02,
            gyro_noise: 0.002,
            acc_bias: 0.05,
            gyro_bias: 0.001,
        }
    }
}

impl ImuParams {
    /// The same model with noise and biases off.
    pub fn noiseless(&self) -> Self {
        Self {
            acc_noise: 0.0,
            gyro_noise: 0.0,
            acc_bias: 0.0,
            gyro_bias: 0.0,
            ..self.clone()
        }
    }

    /// The constant accelerometer (m/s^2) and gyroscope (rad/s) biases of a run with
    /// `seed`, body frame: what a bias estimate is checked against.
    pub fn biases(&self, seed: u64) -> (Vector3<f64>, Vector3<f64>) {
        let mut rng = stream(seed, u64::MAX);
        let acc = random_unit(&mut rng) * self.acc_bias;
        let gyro = random_unit(&mut rng) * self.gyro_bias;
        (acc, gyro)
    }

    /// Checks every parameter; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            (100.0..=400.0).contains(&self.rate_hz),
            "imu-rate-hz",
            self.rate_hz,
            "100 to 400 Hz",
        )?;
        for (name, value) in [
            ("acc-noise", self.acc_noise),
            ("gyro-noise", self.gyro_noise),
            ("acc-bias", self.acc_bias),
            ("gyro-bias", self.gyro_bias),
        ] {
            ensure(
                value.is_finite() && (0.0..=10.0).contains(&value),
                name,
                value,
                "0 to 10",
            )?;
        }
        Ok(())
    }
}

/// Gravity in the map frame when the world (gravity-aligned) frame is tilted against
/// the map by `roll`, `pitch` radians: `R_world_map = Ry(pitch) Rx(roll)`.
pub fn gravity_in_map(roll: f64, pitch: f64) -> Vector3<f64> {
    let world_from_map = Rotation3::from_euler_angles(roll, pitch, 0.0);
    world_from_map.inverse() * Vector3::new(0.0, 0.0, -GRAVITY)
}

fn random_unit(rng: &mut rand::rngs::StdRng) -> Vector3<f64> {
    Vector3::new(gaussian(rng), gaussian(rng), gaussian(rng))
        .try_normalize(1e-12)
        .unwrap_or(Vector3::x())
}

/// IMU samples from `t0` to `t1` inclusive at `params.rate_hz`.
pub fn imu_samples(
    trajectory: &Trajectory,
    params: &ImuParams,
    gravity_map: &Vector3<f64>,
    t0: f64,
    t1: f64,
    seed: u64,
) -> Vec<ImuSample> {
    let (acc_bias, gyro_bias) = params.biases(seed);
    let mut rng = stream(seed, u64::MAX);
    // The same stream drew the biases first.
    random_unit(&mut rng);
    random_unit(&mut rng);
    let count = ((t1 - t0) * params.rate_hz).floor() as usize + 1;
    (0..count)
        .map(|k| {
            let t = t0 + k as f64 / params.rate_hz;
            let rotation = trajectory.pose(t).rotation;
            let specific_force = rotation.inverse() * (trajectory.acceleration(t) - gravity_map);
            let noise = |rng: &mut rand::rngs::StdRng, sigma: f64| {
                Vector3::new(gaussian(rng), gaussian(rng), gaussian(rng)) * sigma
            };
            let acc = specific_force + acc_bias + noise(&mut rng, params.acc_noise);
            let gyro = trajectory.body_rate(t) + gyro_bias + noise(&mut rng, params.gyro_noise);
            ImuSample {
                t,
                acc: acc.into(),
                gyro: gyro.into(),
            }
        })
        .collect()
}
