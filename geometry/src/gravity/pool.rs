//! Filling the pool from an IMU stream and the keyframes' times and poses.

use serde::Serialize;

use super::motion::compensated_sample;
use super::{GravityAligner, ImuWindow, KfAccSample, MotionModel};
use crate::KeyframeId;
use crate::geometry::Pose;
use crate::imu::ImuSample;

/// A keyframe's id, time (seconds, the IMU's clock) and pose `T_map_body`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeStamp {
    /// Keyframe id.
    pub id: KeyframeId,
    /// Time, seconds.
    pub t: f64,
    /// `T_map_body`.
    pub pose: Pose,
}

/// What [`fill_pool`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct PoolFill {
    /// Keyframes offered.
    pub keyframes: usize,
    /// Keyframes pooled (their window had samples, compensated when asked for).
    pub with_samples: usize,
    /// Of those, motion-compensated.
    pub compensated: usize,
    /// Keyframes whose window had samples but was left out: motion compensation was on
    /// and the trajectory does not cover the window (the first pose's window has no pose
    /// before it), so its platform acceleration cannot be removed (the served pool
    /// leaves such windows out too).
    pub skipped: usize,
    /// IMU samples averaged in all.
    pub samples_used: usize,
}

/// Adds every keyframe with IMU samples to the pool: keyframe `k` averages the
/// samples in `(t_{k-1}, t_k]` (the first keyframe a window as long as the next gap, or
/// 1 s alone). With `motion` and `motion_compensation` on, samples are rotated by the
/// trajectory's attitude at their time and the platform's mean acceleration over the
/// window is removed ([`super::motion::compensated_sample`]); windows the trajectory
/// does not cover are left out ([`PoolFill::skipped`]), as the served pool leaves them
/// out (docs/DESIGN.md#gravity): a raw mean of a moving platform would pull the
/// estimate off, all the more as the window of a keyframe at the first pose holds one
/// sample, its spread floored at [`super::MIN_ACC_STD`] (on the simulated campus about
/// four times the weight of a one-second window). Without `motion` (or with
/// compensation off) every window with samples is pooled raw.
pub fn fill_pool(
    aligner: &mut GravityAligner,
    keyframes: &[KeyframeStamp],
    imu: &[ImuSample],
    motion: Option<&MotionModel>,
) -> PoolFill {
    let sorted_imu;
    let imu = if imu.is_sorted_by(|a, b| a.t <= b.t) {
        imu
    } else {
        sorted_imu = ImuWindow::new(imu.to_vec());
        sorted_imu.samples()
    };
    let mut order: Vec<&KeyframeStamp> = keyframes.iter().filter(|k| k.t.is_finite()).collect();
    order.sort_by(|a, b| a.t.total_cmp(&b.t));
    let motion = motion.filter(|_| aligner.params().motion_compensation);
    let mut fill = PoolFill {
        keyframes: keyframes.len(),
        ..PoolFill::default()
    };
    for (k, kf) in order.iter().enumerate() {
        let t_prev = match k {
            0 => kf.t - order.get(1).map_or(1.0, |next| next.t - kf.t),
            _ => order[k - 1].t,
        };
        let window = ImuWindow::cut(imu, t_prev, kf.t);
        let sample = match motion {
            Some(m) => match compensated_sample(&window, t_prev, &kf.pose, m) {
                Some(sample) => {
                    fill.compensated += 1;
                    sample
                }
                None => {
                    fill.skipped += usize::from(!window.is_empty());
                    continue;
                }
            },
            None => match KfAccSample::from_window(&window) {
                Some(sample) => sample,
                None => continue,
            },
        };
        fill.with_samples += 1;
        fill.samples_used += sample.n;
        aligner.on_new_keyframe_raw(kf.id, sample);
    }
    fill
}
