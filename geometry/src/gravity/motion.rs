//! The platform's own acceleration, from a timestamped trajectory: what an accelerometer
//! reads on top of gravity while the platform speeds up, slows down or turns.

use nalgebra::{UnitQuaternion, Vector3};

use super::{ImuWindow, KfAccSample};
use crate::geometry::Pose;

/// Poses over time with velocities by finite differences (central inside, second order
/// one-sided at the ends): the mean acceleration over any interval the trajectory
/// covers, and the attitude at any time in it.
#[derive(Debug, Clone)]
pub struct MotionModel {
    times: Vec<f64>,
    velocities: Vec<Vector3<f64>>,
    rotations: Vec<UnitQuaternion<f64>>,
}

impl MotionModel {
    /// From `(time, pose)` pairs in any order; repeated times keep the first pose.
    /// `None` with fewer than two distinct finite times.
    pub fn new(poses: impl IntoIterator<Item = (f64, Pose)>) -> Option<Self> {
        let mut samples: Vec<(f64, Pose)> =
            poses.into_iter().filter(|(t, _)| t.is_finite()).collect();
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        samples.dedup_by(|later, earlier| later.0 == earlier.0);
        if samples.len() < 2 {
            return None;
        }
        let last = samples.len() - 1;
        let t = |i: usize| samples[i].0;
        let p = |i: usize| samples[i].1.translation.vector;
        // Central differences inside; at the ends (with three poses) the slope of the
        // parabola through the end and its two neighbours: a two-pose difference there
        // errs by half the acceleration times the spacing, which a run starting from
        // rest turned into its first window's error (docs/DESIGN.md#gravity).
        let velocities = (0..=last)
            .map(|i| match (i == 0 || i == last) && last >= 2 {
                true => {
                    let (a, b, c) = if i == 0 {
                        (0, 1, 2)
                    } else {
                        (last, last - 1, last - 2)
                    };
                    let (h1, h2) = (t(b) - t(a), t(c) - t(b));
                    p(a) * (-(2.0 * h1 + h2) / (h1 * (h1 + h2)))
                        + p(b) * ((h1 + h2) / (h1 * h2))
                        + p(c) * (-h1 / (h2 * (h1 + h2)))
                }
                false => {
                    let (a, b) = (i.saturating_sub(1), (i + 1).min(last));
                    (p(b) - p(a)) / (t(b) - t(a))
                }
            })
            .collect();
        Some(Self {
            times: samples.iter().map(|s| s.0).collect(),
            velocities,
            rotations: samples.iter().map(|s| s.1.rotation).collect(),
        })
    }

    /// First time covered, seconds.
    pub fn start(&self) -> f64 {
        self.times[0]
    }

    /// Last time covered, seconds.
    pub fn end(&self) -> f64 {
        self.times[self.times.len() - 1]
    }

    /// The samples around `t` and the fraction of the way from the first to the second,
    /// or `None` outside the trajectory.
    fn bracket(&self, t: f64) -> Option<(usize, f64)> {
        if !(self.start()..=self.end()).contains(&t) {
            return None;
        }
        let i = self
            .times
            .partition_point(|&s| s <= t)
            .clamp(1, self.times.len() - 1);
        let (t0, t1) = (self.times[i - 1], self.times[i]);
        Some((i, (t - t0) / (t1 - t0)))
    }

    /// Velocity at `t` (linear between samples), or `None` outside the trajectory.
    pub fn velocity(&self, t: f64) -> Option<Vector3<f64>> {
        let (i, f) = self.bracket(t)?;
        Some(self.velocities[i - 1] * (1.0 - f) + self.velocities[i] * f)
    }

    /// Attitude `R_map_body` at `t` (slerp between samples), or `None` outside.
    pub fn rotation(&self, t: f64) -> Option<UnitQuaternion<f64>> {
        let (i, f) = self.bracket(t)?;
        Some(self.rotations[i - 1].slerp(&self.rotations[i], f))
    }

    /// Mean acceleration over `[t0, t1]` (map frame, m/s^2): the velocity change over
    /// the interval's length. `None` outside the trajectory or for an empty interval.
    pub fn mean_acceleration(&self, t0: f64, t1: f64) -> Option<Vector3<f64>> {
        if t1 <= t0 {
            return None;
        }
        Some((self.velocity(t1)? - self.velocity(t0)?) / (t1 - t0))
    }
}

/// A keyframe's accelerometer statistics with the platform's motion removed: each
/// sample is rotated into the map with the attitude at its time, the mean platform
/// acceleration over the window `(t_prev, t_kf]` is subtracted, and the result is
/// expressed in the keyframe's body (`pose`) so the aligner's `R_k a` gives it back.
/// Samples outside the trajectory are left out; `None` when none remain.
pub fn compensated_sample(
    window: &ImuWindow,
    t_prev: f64,
    pose: &Pose,
    motion: &MotionModel,
) -> Option<KfAccSample> {
    // Each finite sample the trajectory covers, rotated into the map at its time.
    let in_map: Vec<(f64, Vector3<f64>)> = window
        .samples()
        .iter()
        .filter(|s| s.acc.iter().all(|a| a.is_finite()))
        .filter_map(|s| Some((s.t, motion.rotation(s.t)? * Vector3::from(s.acc))))
        .collect();
    let t_kf = in_map.last()?.0;
    let platform = motion.mean_acceleration(t_prev.max(motion.start()), t_kf)?;
    let mean = in_map.iter().map(|(_, a)| a).sum::<Vector3<f64>>() / in_map.len() as f64;
    // The magnitude spread (shakiness) is the window's, as without compensation.
    let raw = KfAccSample::from_window(window)?;
    Some(KfAccSample {
        a_body: pose.rotation.inverse() * (mean - platform),
        n: in_map.len(),
        ..raw
    })
}
