//! Accelerometer windows: the IMU samples between two keyframes, and their statistics.

use nalgebra::Vector3;

use crate::imu::ImuSample;

/// Time-sorted IMU samples of one keyframe.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImuWindow {
    samples: Vec<ImuSample>,
}

impl ImuWindow {
    /// A window of `samples`, sorted by time here (stable, so equal stamps keep order).
    pub fn new(mut samples: Vec<ImuSample>) -> Self {
        samples.sort_by(|a, b| a.t.total_cmp(&b.t));
        Self { samples }
    }

    /// The half-open window `(t_prev_kf, t_kf]` of a time-sorted `stream`.
    pub fn cut(stream: &[ImuSample], t_prev_kf: f64, t_kf: f64) -> Self {
        let start = stream.partition_point(|s| s.t <= t_prev_kf);
        let end = stream.partition_point(|s| s.t <= t_kf).max(start);
        Self {
            samples: stream[start..end].to_vec(),
        }
    }

    /// The samples, oldest first.
    pub fn samples(&self) -> &[ImuSample] {
        &self.samples
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True without samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

/// One keyframe's accelerometer statistics, body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KfAccSample {
    /// Mean specific force, m/s^2.
    pub a_body: Vector3<f64>,
    /// Population spread of the sample magnitudes about `|a_body|`, m/s^2 (>= 0.01).
    pub a_std: f64,
    /// Samples averaged.
    pub n: usize,
}

/// Floor of [`KfAccSample::a_std`]: a perfectly quiet window is not infinitely trusted.
pub const MIN_ACC_STD: f64 = 0.01;

impl KfAccSample {
    /// Statistics of a window's finite samples; `None` when it has none.
    pub fn from_window(window: &ImuWindow) -> Option<Self> {
        let acc: Vec<Vector3<f64>> = window
            .samples()
            .iter()
            .map(|s| Vector3::from(s.acc))
            .filter(|a| a.iter().all(|c| c.is_finite()))
            .collect();
        if acc.is_empty() {
            return None;
        }
        let n = acc.len() as f64;
        let a_body = acc.iter().sum::<Vector3<f64>>() / n;
        let mean_norm = a_body.norm();
        let variance = acc
            .iter()
            .map(|a| (a.norm() - mean_norm).powi(2))
            .sum::<f64>()
            / n;
        Some(Self {
            a_body,
            a_std: variance.sqrt().max(MIN_ACC_STD),
            n: acc.len(),
        })
    }
}
