//! Gravity from a pool of per-keyframe accelerometer means (MOLA's `GravityMapAligner`,
//! ARCHITECTURE section 8), plus motion compensation: the platform's own acceleration,
//! known from the pose trajectory, is removed from each mean before pooling.
//!
//! ```
//! use kfmap_shared::gravity::{GravityAligner, GravityParams, KfAccSample};
//! use kfmap_shared::geometry::Pose;
//! use nalgebra::Vector3;
//! use std::collections::BTreeMap;
//!
//! let mut aligner = GravityAligner::new(GravityParams::default()).unwrap();
//! let mut poses = BTreeMap::new();
//! for id in 0..12 {
//!     // A level platform reads +9.81 m/s^2 up.
//!     aligner.on_new_keyframe_raw(id, KfAccSample { a_body: Vector3::new(0.0, 0.0, 9.81), a_std: 0.02, n: 100 });
//!     poses.insert(id, Pose::identity());
//! }
//! let correction = aligner.estimate_global_correction(&poses).unwrap();
//! assert!(correction.roll_deg().abs() < 1e-9 && correction.pitch_deg().abs() < 1e-9);
//! ```

mod motion;
mod pool;
#[cfg(test)]
mod tests;
mod window;

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::KeyframeId;
use crate::geometry::Pose;
use crate::options::{InvalidOption, ensure};
pub use motion::{MotionModel, compensated_sample};
pub use pool::{KeyframeStamp, PoolFill, fill_pool};
pub use window::{ImuWindow, KfAccSample, MIN_ACC_STD};

/// Aligner parameters (defaults from ARCHITECTURE section 8).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct GravityParams {
    /// Pool members the global estimate needs, at least.
    pub min_keyframes: usize,
    /// Huber threshold on `|R_i a_i - m|`, m/s^2.
    pub huber_threshold_mps2: f64,
    /// Keyframes shakier than this (std of |a|, m/s^2) keep 1e-3 of their weight.
    pub max_kf_acc_std_mps2: f64,
    /// Reweighting iterations after the seed-weighted mean.
    pub irls_iterations: usize,
    /// Gravity shorter than this, or this close to +Z once normalized, needs no rotation.
    pub axis_eps: f64,
    /// Remove the platform's acceleration (from poses with timestamps) before pooling.
    pub motion_compensation: bool,
}

impl Default for GravityParams {
    fn default() -> Self {
        Self {
            min_keyframes: 10,
            huber_threshold_mps2: 0.5,
            max_kf_acc_std_mps2: 1.5,
            irls_iterations: 3,
            axis_eps: 1e-9,
            motion_compensation: true,
        }
    }
}

impl GravityParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure(
            self.min_keyframes >= 2,
            "min-keyframes",
            self.min_keyframes,
            "at least 2",
        )?;
        ensure(
            positive(self.huber_threshold_mps2),
            "huber-threshold-mps2",
            self.huber_threshold_mps2,
            "a finite value > 0 m/s^2",
        )?;
        ensure(
            positive(self.max_kf_acc_std_mps2),
            "max-kf-acc-std-mps2",
            self.max_kf_acc_std_mps2,
            "a finite value > 0 m/s^2",
        )?;
        ensure(
            self.irls_iterations <= 100,
            "irls-iterations",
            self.irls_iterations,
            "0 to 100",
        )?;
        ensure(
            positive(self.axis_eps) && self.axis_eps < 0.1,
            "axis-eps",
            self.axis_eps,
            "a value in (0, 0.1)",
        )
    }
}

/// How trustworthy an estimate is: who contributed and how much they disagree.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PoolHealth {
    /// Keyframes used (in the pool and with a pose).
    pub members: usize,
    /// Members within the Huber threshold of the estimate.
    pub inliers: usize,
    /// Sum of the final weights, relative to the heaviest member (1 = one full member).
    pub effective_weight: f64,
    /// Weighted RMS of `|R_i a_i - g|`, m/s^2.
    pub spread_mps2: f64,
    /// Weighted RMS angle between `R_i a_i` and `g`, degrees.
    pub spread_deg: f64,
}

/// A gravity estimate: the pooled specific force of a resting platform (points up,
/// about 9.81 m/s^2 long), map frame, not normalized.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityEstimate {
    /// The estimate, m/s^2.
    pub g: Vector3<f64>,
    /// Pool health at the estimate.
    pub health: PoolHealth,
}

/// The rotation taking the map to a gravity-aligned frame (+Z up), yaw exactly 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityCorrection {
    /// `R = Ry(pitch) Rx(roll)`; left-multiply poses by it.
    pub rotation: Rotation3<f64>,
    /// Roll, radians.
    pub roll: f64,
    /// Pitch, radians.
    pub pitch: f64,
    /// The estimate it corrects.
    pub estimate: GravityEstimate,
}

impl GravityCorrection {
    /// Roll in degrees.
    pub fn roll_deg(&self) -> f64 {
        self.roll.to_degrees()
    }

    /// Pitch in degrees.
    pub fn pitch_deg(&self) -> f64 {
        self.pitch.to_degrees()
    }

    /// Yaw of the rotation matrix, `atan2(R10, R00)`: 0 by construction.
    pub fn yaw(&self) -> f64 {
        let m = self.rotation.matrix();
        m[(1, 0)].atan2(m[(0, 0)])
    }
}

/// Roll and pitch of the rotation sending `g` to +Z, with yaw 0; `(0, 0)` (identity)
/// when `|g| < eps` or the unit `g` is within `eps` of +Z.
pub fn roll_pitch_from_gravity(g: &Vector3<f64>, eps: f64) -> (f64, f64) {
    let norm = g.norm();
    if norm < eps || (g / norm - Vector3::z()).norm() < eps {
        return (0.0, 0.0);
    }
    let roll = g.y.atan2(g.z);
    let pitch = (-g.x).atan2((g.y * g.y + g.z * g.z).sqrt());
    (roll, pitch)
}

/// `R = Ry(pitch) Rx(roll)` with the roll and pitch of [`roll_pitch_from_gravity`]:
/// sends `g` to +Z. Built entry by entry so the yaw entry `R10` is exactly 0.
pub fn rotation_from_gravity(g: &Vector3<f64>, eps: f64) -> Rotation3<f64> {
    let (roll, pitch) = roll_pitch_from_gravity(g, eps);
    rotation_from_roll_pitch(roll, pitch)
}

fn rotation_from_roll_pitch(roll: f64, pitch: f64) -> Rotation3<f64> {
    let (sr, cr) = roll.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    #[rustfmt::skip]
    let m = Matrix3::new(
        cp,  sp * sr, sp * cr,
        0.0, cr,      -sr,
        -sp, cp * sr, cp * cr,
    );
    Rotation3::from_matrix_unchecked(m)
}

/// The per-keyframe accelerometer pool and the robust estimates over it.
#[derive(Debug, Clone)]
pub struct GravityAligner {
    params: GravityParams,
    pool: BTreeMap<KeyframeId, KfAccSample>,
}

/// One pool member in the map frame, with its seed weight.
struct Member {
    g: Vector3<f64>,
    seed: f64,
}

impl GravityAligner {
    /// An empty pool; the parameters are validated.
    pub fn new(params: GravityParams) -> Result<Self, InvalidOption> {
        params.validate()?;
        Ok(Self {
            params,
            pool: BTreeMap::new(),
        })
    }

    /// The parameters.
    pub fn params(&self) -> &GravityParams {
        &self.params
    }

    /// Adds (or replaces) a keyframe's statistics from its window; an empty window adds
    /// nothing. Returns whether a sample was stored.
    pub fn on_new_keyframe(&mut self, id: KeyframeId, window: &ImuWindow) -> bool {
        match KfAccSample::from_window(window) {
            Some(sample) => {
                self.on_new_keyframe_raw(id, sample);
                true
            }
            None => false,
        }
    }

    /// Adds (or replaces) a keyframe's precomputed statistics.
    pub fn on_new_keyframe_raw(&mut self, id: KeyframeId, sample: KfAccSample) {
        self.pool.insert(id, sample);
    }

    /// Forgets a keyframe.
    pub fn on_keyframe_dropped(&mut self, id: KeyframeId) {
        self.pool.remove(&id);
    }

    /// Empties the pool.
    pub fn clear(&mut self) {
        self.pool.clear();
    }

    /// Pool members.
    pub fn size(&self) -> usize {
        self.pool.len()
    }

    /// True when `id` has a sample.
    pub fn has(&self, id: KeyframeId) -> bool {
        self.pool.contains_key(&id)
    }

    /// The pool, by keyframe id.
    pub fn samples(&self) -> &BTreeMap<KeyframeId, KfAccSample> {
        &self.pool
    }

    /// Robust gravity over every pooled keyframe with a pose; `None` with fewer than
    /// `min_keyframes` of them.
    pub fn estimate_gravity_vector(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
    ) -> Option<GravityEstimate> {
        self.estimate_over(
            poses.iter().map(|(&id, p)| (id, p)),
            self.params.min_keyframes,
        )
    }

    /// Robust gravity over the keyframes `ids` (those pooled and with a pose); `None`
    /// with fewer than `max(2, min_pool)` of them.
    pub fn estimate_gravity_vector_over_window(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
        ids: &[KeyframeId],
        min_pool: usize,
    ) -> Option<GravityEstimate> {
        self.estimate_over(
            ids.iter().filter_map(|id| Some((*id, poses.get(id)?))),
            min_pool,
        )
    }

    /// The rotation making the whole map +Z up, or `None` as for
    /// [`Self::estimate_gravity_vector`].
    pub fn estimate_global_correction(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
    ) -> Option<GravityCorrection> {
        self.estimate_gravity_vector(poses)
            .map(|e| self.correction(e))
    }

    /// A correction per pooled keyframe from the keyframes within `half_width` places of
    /// it (pose ids sorted, window truncated at the ends); keyframes whose window has
    /// fewer than `min_pool_per_kf` members are left out.
    pub fn estimate_per_kf_correction(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
        half_width: usize,
        min_pool_per_kf: usize,
    ) -> BTreeMap<KeyframeId, GravityCorrection> {
        let ids: Vec<KeyframeId> = poses.keys().copied().collect();
        ids.iter()
            .enumerate()
            .filter(|(_, id)| self.has(**id))
            .filter_map(|(k, &id)| {
                let window =
                    &ids[k.saturating_sub(half_width)..(k + half_width + 1).min(ids.len())];
                let estimate =
                    self.estimate_gravity_vector_over_window(poses, window, min_pool_per_kf)?;
                Some((id, self.correction(estimate)))
            })
            .collect()
    }

    fn correction(&self, estimate: GravityEstimate) -> GravityCorrection {
        let (roll, pitch) = roll_pitch_from_gravity(&estimate.g, self.params.axis_eps);
        GravityCorrection {
            rotation: rotation_from_roll_pitch(roll, pitch),
            roll,
            pitch,
            estimate,
        }
    }

    /// Seed-weighted mean, then Huber IRLS on `|g_i - m|`.
    fn estimate_over<'p>(
        &self,
        keyframes: impl Iterator<Item = (KeyframeId, &'p Pose)>,
        min_pool: usize,
    ) -> Option<GravityEstimate> {
        let members: Vec<Member> = keyframes
            .filter_map(|(id, pose)| {
                let s = self.pool.get(&id)?;
                let mut seed = 1.0 / (s.a_std * s.a_std).max(1e-6);
                if s.a_std > self.params.max_kf_acc_std_mps2 {
                    seed *= 1e-3;
                }
                Some(Member {
                    g: pose.rotation * s.a_body,
                    seed,
                })
            })
            .collect();
        if members.len() < min_pool.max(2) {
            return None;
        }
        let h = self.params.huber_threshold_mps2;
        let weights = |m: &Vector3<f64>| -> Vec<f64> {
            members
                .iter()
                .map(|x| {
                    let r = (x.g - m).norm();
                    x.seed * if r <= h { 1.0 } else { h / r }
                })
                .collect()
        };
        let weighted_mean = |w: &[f64]| -> Vector3<f64> {
            let total: f64 = w.iter().sum();
            members
                .iter()
                .zip(w)
                .map(|(x, &wi)| x.g * wi)
                .sum::<Vector3<f64>>()
                / total
        };
        let seeds: Vec<f64> = members.iter().map(|x| x.seed).collect();
        let mut g = weighted_mean(&seeds);
        for _ in 0..self.params.irls_iterations {
            g = weighted_mean(&weights(&g));
        }
        Some(GravityEstimate {
            g,
            health: health(&members, &weights(&g), &g, h),
        })
    }
}

fn health(members: &[Member], w: &[f64], g: &Vector3<f64>, huber: f64) -> PoolHealth {
    let total: f64 = w.iter().sum();
    let heaviest = members.iter().map(|m| m.seed).fold(0.0, f64::max);
    let mean_sq = |f: &dyn Fn(&Member) -> f64| {
        members
            .iter()
            .zip(w)
            .map(|(m, wi)| wi * f(m).powi(2))
            .sum::<f64>()
            / total
    };
    PoolHealth {
        members: members.len(),
        inliers: members.iter().filter(|m| (m.g - g).norm() <= huber).count(),
        effective_weight: total / heaviest,
        spread_mps2: mean_sq(&|m| (m.g - g).norm()).sqrt(),
        spread_deg: mean_sq(&|m| m.g.angle(g).to_degrees()).sqrt(),
    }
}
