//! Gravity from a pool of per-keyframe accelerometer means (MOLA's `GravityMapAligner`,
//! docs/DESIGN.md#gravity), plus motion compensation: the platform's own acceleration,
//! known from the pose trajectory, is removed from each mean before pooling.
//!
//! ```
//! use kfmap_geometry::gravity::{GravityAligner, GravityParams, KfAccSample};
//! use kfmap_geometry::geometry::Pose;
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

mod live;
mod motion;
mod pool;
#[cfg(test)]
mod tests;
mod window;

use std::collections::BTreeMap;

use std::ops::AddAssign;

use nalgebra::{Matrix3, Matrix6, Rotation3, UnitQuaternion, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use crate::KeyframeId;
use crate::geometry::Pose;
use crate::options::{InvalidOption, ensure};
pub use live::{LiveAnswer, LiveGravity, MAX_MEMBERS};
pub use motion::{MotionModel, compensated_sample};
pub use pool::{KeyframeStamp, PoolFill, fill_pool};
pub use window::{ImuWindow, KfAccSample, MIN_ACC_STD};

/// Standard gravity, m/s^2 (the magnitude an accelerometer at rest reads).
pub const STANDARD_GRAVITY_MPS2: f64 = 9.80665;

/// Aligner parameters (defaults from docs/DESIGN.md#gravity).
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
    /// Estimate a constant body-frame accelerometer bias jointly with gravity (it shows
    /// as the keyframes' readings disagreeing as the platform turns).
    pub estimate_accel_bias: bool,
    /// Prior standard deviation of each bias axis, m/s^2: what pins the bias where the
    /// motion so far cannot tell it from gravity.
    pub accel_bias_prior_mps2: f64,
    /// Local gravity magnitude, m/s^2, and how well it is known: it separates the bias
    /// along gravity from gravity itself.
    pub gravity_mps2: f64,
    /// Standard deviation of `gravity-mps2`, m/s^2.
    pub gravity_sigma_mps2: f64,
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
            estimate_accel_bias: true,
            accel_bias_prior_mps2: 0.1,
            gravity_mps2: STANDARD_GRAVITY_MPS2,
            gravity_sigma_mps2: 0.02,
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
            positive(self.accel_bias_prior_mps2),
            "accel-bias-prior-mps2",
            self.accel_bias_prior_mps2,
            "a finite value > 0 m/s^2",
        )?;
        ensure(
            positive(self.gravity_mps2),
            "gravity-mps2",
            self.gravity_mps2,
            "a finite value > 0 m/s^2",
        )?;
        ensure(
            positive(self.gravity_sigma_mps2),
            "gravity-sigma-mps2",
            self.gravity_sigma_mps2,
            "a finite value > 0 m/s^2",
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
    /// The accelerometer bias removed from every reading, body frame.
    pub accel_bias: AccelBias,
}

/// The accelerometer bias an estimate used.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccelBias {
    /// The bias, body frame, m/s^2 (zero when not estimated).
    pub mps2: Vector3<f64>,
    /// Its standard deviation per body axis, m/s^2 (`None`: not estimated here).
    pub sigma_mps2: Option<Vector3<f64>>,
    /// True when the motion so far determines every axis of the bias (the keyframes
    /// turned enough), rather than the prior.
    pub observable: bool,
}

impl AccelBias {
    /// No bias, not estimated.
    pub const NONE: AccelBias = AccelBias {
        mps2: Vector3::new(0.0, 0.0, 0.0),
        sigma_mps2: None,
        observable: false,
    };
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

/// Contiguous blocks of pool members left out in turn to judge the bias's spread.
const JACKKNIFE_BLOCKS: usize = 5;

/// One pool member: its keyframe's attitude and mean reading, with its seed weight.
#[derive(Clone)]
struct Member {
    rotation: UnitQuaternion<f64>,
    a_body: Vector3<f64>,
    seed: f64,
}

impl Member {
    /// Its reading, less `bias`, in the map frame.
    fn up(&self, bias: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * (self.a_body - bias)
    }
}

/// How an estimate treats the accelerometer bias.
#[derive(Debug, Clone, Copy)]
enum BiasMode {
    /// Estimated jointly with gravity.
    Estimate,
    /// Taken as known.
    Fixed(AccelBias),
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

    /// Robust gravity over every pooled keyframe with a pose, with the accelerometer
    /// bias when `estimate-accel-bias` is on; `None` with fewer than `min_keyframes` of
    /// them.
    pub fn estimate_gravity_vector(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
    ) -> Option<GravityEstimate> {
        let bias = if self.params.estimate_accel_bias {
            BiasMode::Estimate
        } else {
            BiasMode::Fixed(AccelBias::NONE)
        };
        self.estimate_over(
            poses.iter().map(|(&id, p)| (id, p)),
            self.params.min_keyframes,
            bias,
        )
    }

    /// The bias of the whole pool's estimate (none when there is no estimate).
    fn pool_bias(&self, poses: &BTreeMap<KeyframeId, Pose>) -> AccelBias {
        self.estimate_gravity_vector(poses)
            .map_or(AccelBias::NONE, |e| e.accel_bias)
    }

    fn estimate_window(
        &self,
        poses: &BTreeMap<KeyframeId, Pose>,
        ids: &[KeyframeId],
        min_pool: usize,
        bias: AccelBias,
    ) -> Option<GravityEstimate> {
        self.estimate_over(
            ids.iter().filter_map(|id| Some((*id, poses.get(id)?))),
            min_pool,
            BiasMode::Fixed(bias),
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
        let bias = self.pool_bias(poses);
        ids.iter()
            .enumerate()
            .filter(|(_, id)| self.has(**id))
            .filter_map(|(k, &id)| {
                let window =
                    &ids[k.saturating_sub(half_width)..(k + half_width + 1).min(ids.len())];
                let estimate = self.estimate_window(poses, window, min_pool_per_kf, bias)?;
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

    /// Seed-weighted mean, then Huber IRLS on `|R_i (a_i - b) - m|`; with
    /// [`BiasMode::Estimate`] each reweighting solves gravity and bias jointly.
    fn estimate_over<'p>(
        &self,
        keyframes: impl Iterator<Item = (KeyframeId, &'p Pose)>,
        min_pool: usize,
        bias: BiasMode,
    ) -> Option<GravityEstimate> {
        let members: Vec<Member> = keyframes
            .filter_map(|(id, pose)| {
                let s = self.pool.get(&id)?;
                let mut seed = 1.0 / (s.a_std * s.a_std).max(1e-6);
                if s.a_std > self.params.max_kf_acc_std_mps2 {
                    seed *= 1e-3;
                }
                Some(Member {
                    rotation: pose.rotation,
                    a_body: s.a_body,
                    seed,
                })
            })
            .collect();
        if members.len() < min_pool.max(2) {
            return None;
        }
        let h = self.params.huber_threshold_mps2;
        let weights = |m: &Vector3<f64>, b: &Vector3<f64>| -> Vec<f64> {
            members
                .iter()
                .map(|x| {
                    let r = (x.up(b) - m).norm();
                    x.seed * if r <= h { 1.0 } else { h / r }
                })
                .collect()
        };
        let mut w: Vec<f64> = members.iter().map(|x| x.seed).collect();
        let mut fit = match bias {
            BiasMode::Fixed(b) => (weighted_mean(&members, &w, &b.mps2), b),
            BiasMode::Estimate => self.solve_with_bias(&members, &w),
        };
        for _ in 0..self.params.irls_iterations {
            w = weights(&fit.0, &fit.1.mps2);
            fit = match bias {
                BiasMode::Fixed(b) => (weighted_mean(&members, &w, &b.mps2), b),
                BiasMode::Estimate => self.solve_with_bias(&members, &w),
            };
        }
        let (g, mut accel_bias) = fit;
        let w = weights(&g, &accel_bias.mps2);
        if matches!(bias, BiasMode::Estimate) {
            self.widen_by_jackknife(&members, &w, &mut accel_bias);
        }
        Some(GravityEstimate {
            g,
            health: health(&members, &w, &g, &accel_bias.mps2, h),
            accel_bias,
        })
    }

    /// Widens the bias sigma to the spread of the estimates with each of
    /// [`JACKKNIFE_BLOCKS`] contiguous blocks of members left out, and clears
    /// `observable` unless that spread is also within a third of the prior. Errors along
    /// a trajectory are correlated: on the real IMU log the two halves' biases differed
    /// by 0.03-0.06 m/s^2 while the residual-based sigma said 0.004.
    fn widen_by_jackknife(&self, members: &[Member], w: &[f64], bias: &mut AccelBias) {
        let k = JACKKNIFE_BLOCKS;
        if members.len() < 2 * k {
            bias.observable = false;
            return;
        }
        let block = |i: usize| i * k / members.len();
        let estimates: Vec<Vector3<f64>> = (0..k)
            .map(|left_out| {
                let (kept, kept_w): (Vec<Member>, Vec<f64>) = members
                    .iter()
                    .zip(w)
                    .enumerate()
                    .filter(|(i, _)| block(*i) != left_out)
                    .map(|(_, (m, wi))| (m.clone(), *wi))
                    .unzip();
                self.solve_with_bias(&kept, &kept_w).1.mps2
            })
            .collect();
        let mean = estimates.iter().sum::<Vector3<f64>>() / k as f64;
        let spread = estimates
            .iter()
            .map(|e| (e - mean).component_mul(&(e - mean)))
            .sum::<Vector3<f64>>()
            * ((k - 1) as f64 / k as f64);
        let jackknife = spread.map(f64::sqrt);
        bias.sigma_mps2 = Some(match bias.sigma_mps2 {
            Some(s) => s.sup(&jackknife),
            None => jackknife,
        });
        bias.observable &= jackknife.max() < self.params.accel_bias_prior_mps2 / 3.0;
    }

    /// Weighted least squares for gravity `m` and bias `b` in `R_i (a_i - b) = m`, with
    /// the bias prior and the known gravity magnitude (Gauss-Newton: only the magnitude
    /// is nonlinear).
    fn solve_with_bias(&self, members: &[Member], w: &[f64]) -> (Vector3<f64>, AccelBias) {
        let p = &self.params;
        let prior = 1.0 / p.accel_bias_prior_mps2.powi(2);
        let magnitude = 1.0 / p.gravity_sigma_mps2.powi(2);
        let mut m = weighted_mean(members, w, &Vector3::zeros());
        let mut b = Vector3::zeros();
        // The data's information on (m, b), plus the magnitude term at the last m.
        let normal = |m: &Vector3<f64>| -> Matrix6<f64> {
            let mut h = Matrix6::zeros();
            for (x, &wi) in members.iter().zip(w) {
                let r = x.rotation.to_rotation_matrix().into_inner();
                h.fixed_view_mut::<3, 3>(0, 0)
                    .add_assign(Matrix3::identity() * wi);
                h.fixed_view_mut::<3, 3>(0, 3).add_assign(r * wi);
                h.fixed_view_mut::<3, 3>(3, 0)
                    .add_assign(r.transpose() * wi);
                h.fixed_view_mut::<3, 3>(3, 3)
                    .add_assign(Matrix3::identity() * wi);
            }
            let u = m.normalize();
            h.fixed_view_mut::<3, 3>(0, 0)
                .add_assign(u * u.transpose() * magnitude);
            h
        };
        for _ in 0..5 {
            let mut h = normal(&m);
            let mut gradient = Vector6::zeros();
            for (x, &wi) in members.iter().zip(w) {
                let r = x.up(&b) - m;
                gradient.fixed_rows_mut::<3>(0).add_assign(-r * wi);
                gradient
                    .fixed_rows_mut::<3>(3)
                    .add_assign(-(x.rotation.inverse() * r) * wi);
            }
            gradient
                .fixed_rows_mut::<3>(0)
                .add_assign(m.normalize() * (m.norm() - p.gravity_mps2) * magnitude);
            gradient.fixed_rows_mut::<3>(3).add_assign(b * prior);
            h.fixed_view_mut::<3, 3>(3, 3)
                .add_assign(Matrix3::identity() * prior);
            let Some(step) = h.cholesky().map(|c| c.solve(&-gradient)) else {
                break;
            };
            m += step.fixed_rows::<3>(0);
            b += step.fixed_rows::<3>(3);
            if step.norm() < 1e-12 {
                break;
            }
        }
        // Uncertainty: the inverse information, scaled by how well the model fits.
        let data = normal(&m);
        let mut full = data;
        full.fixed_view_mut::<3, 3>(3, 3)
            .add_assign(Matrix3::identity() * prior);
        let dof = (3 * members.len()).saturating_sub(6).max(1) as f64;
        let chi2: f64 = members
            .iter()
            .zip(w)
            .map(|(x, &wi)| wi * (x.up(&b) - m).norm_squared())
            .sum();
        let sigma = full.try_inverse().map(|cov| {
            let scale = (chi2 / dof).max(f64::EPSILON);
            Vector3::from_fn(|i, _| (cov[(3 + i, 3 + i)] * scale).sqrt())
        });
        // Observable when the data (and the magnitude) alone pin every bias direction
        // ten times tighter than the prior does, and the fit leaves the bias known to a
        // third of the prior (a poor fit makes even well-excited directions uncertain).
        let schur = data.fixed_view::<3, 3>(0, 0).try_inverse().map(|mm_inv| {
            data.fixed_view::<3, 3>(3, 3)
                - data.fixed_view::<3, 3>(3, 0) * mm_inv * data.fixed_view::<3, 3>(0, 3)
        });
        let excited = schur.is_some_and(|s| s.symmetric_eigenvalues().min() >= 10.0 * prior);
        let known = sigma.is_some_and(|s| s.max() < p.accel_bias_prior_mps2 / 3.0);
        let observable = excited && known;
        (
            m,
            AccelBias {
                mps2: b,
                sigma_mps2: sigma,
                observable,
            },
        )
    }
}

/// `sum w_i R_i (a_i - bias) / sum w_i`.
fn weighted_mean(members: &[Member], w: &[f64], bias: &Vector3<f64>) -> Vector3<f64> {
    let total: f64 = w.iter().sum();
    members
        .iter()
        .zip(w)
        .map(|(x, &wi)| x.up(bias) * wi)
        .sum::<Vector3<f64>>()
        / total
}

fn health(
    members: &[Member],
    w: &[f64],
    g: &Vector3<f64>,
    bias: &Vector3<f64>,
    huber: f64,
) -> PoolHealth {
    let total: f64 = w.iter().sum();
    let heaviest = members.iter().map(|m| m.seed).fold(0.0, f64::max);
    let mean_sq = |f: &dyn Fn(&Vector3<f64>) -> f64| {
        members
            .iter()
            .zip(w)
            .map(|(m, wi)| wi * f(&m.up(bias)).powi(2))
            .sum::<f64>()
            / total
    };
    PoolHealth {
        members: members.len(),
        inliers: members
            .iter()
            .filter(|m| (m.up(bias) - g).norm() <= huber)
            .count(),
        effective_weight: total / heaviest,
        spread_mps2: mean_sq(&|up| (up - g).norm()).sqrt(),
        spread_deg: mean_sq(&|up| up.angle(g).to_degrees()).sqrt(),
    }
}
