//! What a localized scan reports about itself: status, fitness, degeneracy and the
//! pose covariance (docs/DESIGN.md#tracking).

use nalgebra::{Matrix3, Matrix6, Vector3};
use serde::Serialize;

use crate::registration::{Constraint, RegistrationResult};

/// How far a localized scan can be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum TrackingStatus {
    /// The pose fits the map well, is constrained in every direction and agrees with
    /// the motion model.
    Ok = 0,
    /// A pose was adopted but one check is marginal (see the reasons): degenerate
    /// geometry, no convergence, fitness below the `ok` level, a correction beyond the
    /// motion model that the wider search confirmed, or the first scans after `lost`.
    Degraded = 1,
    /// No pose was adopted: the reported pose is the prediction.
    Lost = 2,
}

impl TrackingStatus {
    /// Every status, by code.
    pub const ALL: [TrackingStatus; 3] = [Self::Ok, Self::Degraded, Self::Lost];

    /// The status of a wire code; `None` for codes this build does not know.
    pub fn from_code(code: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|s| *s as u32 == code)
    }

    /// Lower-case name, as in JSON output.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ok => "ok",
            Self::Degraded => "degraded",
            Self::Lost => "lost",
        }
    }
}

/// Why a scan is not `ok`, and what the retry ladder did: a set of bits (stable on
/// the wire).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Reasons(pub u32);

impl Reasons {
    /// A block of the Hessian is below the degeneracy ratio.
    pub const DEGENERATE: Self = Self(1);
    /// The solver stopped at its iteration limit.
    pub const NOT_CONVERGED: Self = Self(1 << 1);
    /// Inlier ratio below the `ok` level (`ok-inlier-ratio`).
    pub const LOW_FITNESS: Self = Self(1 << 2);
    /// Inlier ratio below the `lost` level, or no correspondences at all.
    pub const NO_FIT: Self = Self(1 << 3);
    /// The correction from the prediction exceeds what the motion model allows.
    pub const IMPLAUSIBLE: Self = Self(1 << 4);
    /// The first registration failed a check and wider hypotheses were tried.
    pub const RETRIED: Self = Self(1 << 5);
    /// Distinct poses fit about equally well.
    pub const AMBIGUOUS: Self = Self(1 << 6);
    /// The tracker was lost and has not yet seen scans agree again.
    pub const RECOVERING: Self = Self(1 << 7);
    /// The Hessian is singular: no covariance.
    pub const SINGULAR: Self = Self(1 << 8);
    /// Inlier ratio well below that of the scans before (`fitness-drop`).
    pub const FITNESS_DROP: Self = Self(1 << 9);
    /// The pose came from global relocalization (no prediction): the motion model
    /// restarted there.
    pub const RELOCALIZED: Self = Self(1 << 10);
    /// The tracker gave up the pose: too many scans in a row were adopted without
    /// fitting the map (not converged, low fitness, fitness falling), so it says `lost`
    /// and looks again instead of following its own prediction.
    pub const UNFIT_STREAK: Self = Self(1 << 11);
    /// Set by the client's tracker: the pose is not pinned where it sits (sliding it
    /// half a metre along its least constrained direction costs too little of what
    /// the map explains, or explains more): a street it may be sliding along.
    pub const UNPINNED: Self = Self(1 << 12);

    const NAMES: [(Self, &'static str); 13] = [
        (Self::DEGENERATE, "degenerate"),
        (Self::NOT_CONVERGED, "not-converged"),
        (Self::LOW_FITNESS, "low-fitness"),
        (Self::NO_FIT, "no-fit"),
        (Self::IMPLAUSIBLE, "implausible"),
        (Self::RETRIED, "retried"),
        (Self::AMBIGUOUS, "ambiguous"),
        (Self::RECOVERING, "recovering"),
        (Self::SINGULAR, "singular"),
        (Self::FITNESS_DROP, "fitness-drop"),
        (Self::RELOCALIZED, "relocalized"),
        (Self::UNFIT_STREAK, "unfit-streak"),
        (Self::UNPINNED, "unpinned"),
    ];

    /// No reason.
    pub const NONE: Self = Self(0);

    /// True when every bit of `other` is set.
    pub fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }

    /// Sets the bits of `other`.
    pub fn insert(&mut self, other: Self) {
        self.0 |= other.0;
    }

    /// The names of the bits set, in bit order (unknown bits are left out).
    pub fn names(self) -> Vec<&'static str> {
        Self::NAMES
            .iter()
            .filter(|(bit, _)| self.contains(*bit))
            .map(|(_, name)| *name)
            .collect()
    }
}

impl std::ops::BitOr for Reasons {
    type Output = Self;

    fn bitor(self, other: Self) -> Self {
        Self(self.0 | other.0)
    }
}

/// The health of one localized scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanHealth {
    /// Whether the pose was adopted and how far to trust it.
    pub status: TrackingStatus,
    /// Why it is not `ok`, and whether the retry ladder ran.
    pub reasons: Reasons,
    /// Scan points with a map partner within the pairing distance, over all (of the
    /// registration the pose came from; of the best rejected one when `lost`).
    pub inlier_ratio: f64,
    /// RMS distance of those pairs, metres.
    pub rmse: f64,
    /// Eigenvalue ratios of the Hessian's rotation and translation blocks.
    pub constraint: Constraint,
    /// True when a ratio is below the degeneracy threshold.
    pub degenerate: bool,
    /// 6x6 covariance of the pose (see [`pose_covariance`]); `None` when the Hessian is
    /// singular or no registration ran.
    pub covariance: Option<Matrix6<f64>>,
    /// How far the pose moved from the prediction: translation plus the chord a point
    /// at [`super::CORRECTION_RANGE_M`] sweeps, metres (of the best rejected pose when
    /// `lost`).
    pub correction: f64,
    /// Registrations run for this scan (1 when the first one passed every check).
    pub registrations: u32,
    /// Solver iterations, summed over those registrations.
    pub iterations: u32,
    /// True when the registration the pose came from converged.
    pub converged: bool,
}

impl ScanHealth {
    /// A `lost` scan for which no registration produced a pose.
    pub fn no_fit(registrations: u32, iterations: u32) -> Self {
        Self {
            status: TrackingStatus::Lost,
            reasons: Reasons::NO_FIT,
            inlier_ratio: 0.0,
            rmse: 0.0,
            constraint: Constraint {
                rotation_ratio: 0.0,
                translation_ratio: 0.0,
            },
            degenerate: true,
            covariance: None,
            correction: 0.0,
            registrations,
            iterations,
            converged: false,
        }
    }
}

/// Side of the cubes the localizer clusters its pairs in for the sandwich covariance,
/// metres: about a wall's or a building face's extent, so that pairs on one surface,
/// whose errors share the surface's offset in the map, count as one draw. On later
/// recordings of simulated drives (DESIGN #covariance) the courtyard's position NEES
/// was 11 with 1 m cubes, 4.9 with 3 m and 2.7 with 10 m (3 when calibrated).
pub const SANDWICH_CLUSTER_M: f64 = 10.0;

/// Variance factor on [`registration_covariance`]: neighbouring cubes of one wall or
/// of the ground still err together, which the cluster scatter cannot see, and the
/// per-pair term counts independent noise a second time. Measured on simulated drives
/// replayed against a map of another recording (DESIGN #covariance): with 4 the mean
/// position NEES is 1.7-4.8 on unchanged worlds (courtyard, street, corridor, two
/// campus runs), 6.9-19 with 1.
pub const COVARIANCE_INFLATION: f64 = 4.0;

/// Rotation variance floor about each horizontal axis of the map, rad^2 ((0.01 deg)^2):
/// roll and pitch err by 0.005-0.015 deg on every simulated site while the residuals
/// say 0.001-0.003 deg, an error shared by the whole ground (the surfel normals of the
/// keyframes it is paired with), one draw per scan that no scatter within the scan can
/// show. Not about the vertical: the heading erred by 0.8-1.4 mdeg RMS on the same
/// sites, where the sandwich alone says 1.1-1.6 and the floor would say 10
/// (docs/DESIGN.md#covariance).
pub const ROTATION_FLOOR_RAD2: f64 =
    (0.01 * std::f64::consts::PI / 180.0) * (0.01 * std::f64::consts::PI / 180.0);

/// What a registration says of its own pose's spread, the sum of two terms:
/// - the inverse Hessian scaled by the residual variance, `sigma^2 H^-1` with
///   `sigma^2 = cost / (3 pairs - 6)` (the cost is already whitened by the pairs'
///   information matrices): what independent noise on every pair leaves;
/// - the cluster-robust sandwich `G / (G - 1) H^-1 M H^-1` over the `G` clusters of
///   the result's [`GradientScatter`] `M`, when the registration asked for it: what
///   errors shared by whole surfaces leave (a wall mapped or seen a little off, clutter
///   that moved), which the first term counts as thousands of independent pairs.
///
/// The first term keeps the sum full rank when a scan falls in few cubes (the scatter
/// of `G` clusters has rank `G - 1`); on many cubes the sum counts independent noise
/// twice, which [`COVARIANCE_INFLATION`] was measured with. Directions the scene
/// barely constrains (a corridor's axis) stay large in both. Same frame and units as
/// [`pose_covariance`]; `None` when the Hessian is singular or there are too few pairs.
///
/// [`GradientScatter`]: crate::registration::GradientScatter
pub fn registration_covariance(result: &RegistrationResult) -> Option<Matrix6<f64>> {
    let dof = 3 * result.pairs;
    if dof <= 6 {
        return None;
    }
    let sigma2 = result.cost / (dof - 6) as f64;
    let inverse = result.hessian.try_inverse()?;
    let mut covariance = inverse * sigma2;
    if let Some(scatter) = result.gradient_scatter.filter(|s| s.clusters >= 2) {
        let g = scatter.clusters as f64;
        covariance += inverse * scatter.matrix * inverse.transpose() * (g / (g - 1.0));
    }
    covariance
        .iter()
        .all(|v| v.is_finite())
        .then_some(covariance)
}

/// The covariance kfmap publishes for a registered pose: [`COVARIANCE_INFLATION`] times
/// [`registration_covariance`], plus [`ROTATION_FLOOR_RAD2`] about the map's two
/// horizontal axes (the rotation block plus `floor (I - u u^T)`, `u` the map's up in
/// the sensor frame). It is the covariance of the right perturbation `T exp(d)`, `d` =
/// (rotation, rad; translation, m) in the sensor frame, rotation first: rad^2, rad m and
/// m^2; `result.pose` is the sensor's pose in the map. `None` when the Hessian is
/// singular or there are too few pairs.
pub fn pose_covariance(result: &RegistrationResult) -> Option<Matrix6<f64>> {
    let mut covariance = registration_covariance(result)? * COVARIANCE_INFLATION;
    let up = result.pose.rotation.inverse() * Vector3::z();
    let floor = (Matrix3::identity() - up * up.transpose()) * ROTATION_FLOOR_RAD2;
    let mut rotation = covariance.fixed_view_mut::<3, 3>(0, 0);
    rotation += floor;
    Some(covariance)
}

/// The covariance as 36 row-major values, zeros when unknown (the wire layout).
pub fn covariance_to_wire(covariance: Option<&Matrix6<f64>>) -> [f64; 36] {
    covariance.map_or([0.0; 36], |c| std::array::from_fn(|i| c[(i / 6, i % 6)]))
}

/// The covariance of 36 row-major wire values; `None` when all are zero (unknown).
pub fn covariance_from_wire(values: &[f64; 36]) -> Option<Matrix6<f64>> {
    values
        .iter()
        .any(|v| *v != 0.0)
        .then(|| Matrix6::from_row_slice(values))
}
