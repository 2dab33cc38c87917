//! One scan's localization with its checks and the retry ladder: register from the
//! prediction; when the result fails a check (fitness, plausibility against the motion
//! model), retry from wider hypotheses (a coarser scan with a larger pairing distance,
//! then yaw hypotheses) and adopt a pose only when the evidence is consistent.

use serde::{Deserialize, Serialize};

use super::health::{Reasons, SANDWICH_CLUSTER_M, ScanHealth, TrackingStatus, pose_covariance};
use crate::cloud::{CloudError, PointCloud};
use crate::geometry::{Pose, rotation_distance, translation_distance};
use crate::motion::{point_displacement, yaw_hypotheses};
use crate::options::{InvalidOption, ensure};
use crate::registration::{RegistrationParams, RegistrationResult};

/// Range at which a correction's rotation is measured, metres: a correction counts as
/// its translation plus the chord a point this far from the sensor sweeps (KISS-ICP's
/// model error at its default range).
pub const CORRECTION_RANGE_M: f64 = 10.0;

/// Thresholds and the retry ladder of scan localization. Client-side and server-side
/// localization use the same values, so both decide alike.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct TrackingParams {
    /// A scan can be `ok` only with at least this fraction of its points paired.
    pub ok_inlier_ratio: f64,
    /// A first registration pairing less than `1 - fitness-drop` times the inlier
    /// ratio the tracker expects (that of the scans before) is retried.
    pub fitness_drop: f64,
    /// Below this fraction the pose is not adopted (`lost`).
    pub lost_inlier_ratio: f64,
    /// Every registration starts with coarse iterations (the scan voxelized at
    /// `coarse-voxel`, pairs up to `coarse-pair-dist`): a wider basin for little cost.
    pub coarse_first: bool,
    /// Voxel of the coarse scan, metres.
    pub coarse_voxel: f64,
    /// Pairing distance of coarse iterations, metres (at least the request's).
    pub coarse_pair_dist: f64,
    /// Coarse iterations at most.
    pub coarse_iterations: usize,
    /// Yaw hypotheses step, degrees (0 turns them off).
    pub yaw_step_deg: f64,
    /// Yaw hypotheses up to this angle either side of the prediction, degrees.
    pub yaw_max_deg: f64,
    /// Two registrations agree when their poses are closer than this, metres...
    pub agree_translation: f64,
    /// ... and this, degrees.
    pub agree_rotation_deg: f64,
    /// A disagreeing registration whose inlier ratio is within this of the best makes
    /// the scan ambiguous.
    pub ambiguity_margin: f64,
}

impl Default for TrackingParams {
    fn default() -> Self {
        Self {
            ok_inlier_ratio: 0.5,
            fitness_drop: 0.15,
            lost_inlier_ratio: 0.3,
            coarse_first: true,
            coarse_voxel: 1.0,
            coarse_pair_dist: 3.0,
            coarse_iterations: 20,
            yaw_step_deg: 15.0,
            yaw_max_deg: 45.0,
            agree_translation: 0.3,
            agree_rotation_deg: 3.0,
            ambiguity_margin: 0.03,
        }
    }
}

impl TrackingParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let ratio = |v: f64| (0.0..=1.0).contains(&v);
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure(
            ratio(self.ok_inlier_ratio),
            "ok-inlier-ratio",
            self.ok_inlier_ratio,
            "0 to 1",
        )?;
        ensure(
            ratio(self.fitness_drop),
            "fitness-drop",
            self.fitness_drop,
            "0 to 1",
        )?;
        ensure(
            ratio(self.lost_inlier_ratio) && self.lost_inlier_ratio <= self.ok_inlier_ratio,
            "lost-inlier-ratio",
            self.lost_inlier_ratio,
            "0 to ok-inlier-ratio",
        )?;
        ensure(
            positive(self.coarse_voxel),
            "coarse-voxel",
            self.coarse_voxel,
            "a finite size > 0 m",
        )?;
        ensure(
            positive(self.coarse_pair_dist) && self.coarse_pair_dist <= 50.0,
            "coarse-pair-dist",
            self.coarse_pair_dist,
            "a distance > 0 and <= 50 m",
        )?;
        ensure(
            self.coarse_iterations >= 1,
            "coarse-iterations",
            self.coarse_iterations,
            "at least 1",
        )?;
        ensure(
            self.yaw_step_deg.is_finite() && self.yaw_step_deg >= 0.0,
            "yaw-step-deg",
            self.yaw_step_deg,
            ">= 0 degrees (0 = off)",
        )?;
        ensure(
            self.yaw_max_deg.is_finite() && (0.0..=180.0).contains(&self.yaw_max_deg),
            "yaw-max-deg",
            self.yaw_max_deg,
            "0 to 180 degrees",
        )?;
        ensure(
            positive(self.agree_translation),
            "agree-translation",
            self.agree_translation,
            "> 0 m",
        )?;
        ensure(
            positive(self.agree_rotation_deg),
            "agree-rotation-deg",
            self.agree_rotation_deg,
            "> 0 degrees",
        )?;
        ensure(
            ratio(self.ambiguity_margin),
            "ambiguity-margin",
            self.ambiguity_margin,
            "0 to 1",
        )
    }

    /// The coarse scan: `points` (sensor frame) voxelized at `coarse-voxel`, view
    /// directions averaged. Client and server build it alike.
    pub fn coarse_scan(
        &self,
        points: &[[f32; 3]],
        view_dirs: Option<&[[f32; 3]]>,
    ) -> Result<PointCloud, CloudError> {
        PointCloud {
            points: points.to_vec(),
            view_dirs: view_dirs.map(<[_]>::to_vec),
            intensity: None,
            time: None,
        }
        .voxel_downsample(self.coarse_voxel)
    }
}

/// What the tracker expects of a scan, from the scans before it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Expectation {
    /// The largest correction from the prediction the motion model allows, metres of
    /// [`point_displacement`] at [`CORRECTION_RANGE_M`]; `None`: no bound (no motion
    /// model yet).
    pub max_correction: Option<f64>,
    /// The inlier ratio of the scans before; `None`: unknown.
    pub inlier_ratio: Option<f64>,
}

/// Which scan one registration pairs and with what settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stage {
    /// The coarse scan (see [`TrackingParams::coarse_scan`]) instead of the scan sent.
    pub coarse: bool,
    /// Pairing distance, metres.
    pub max_pair_dist: f64,
    /// Iterations at most.
    pub max_iterations: usize,
}

impl Stage {
    /// The registration settings of this stage: the localization defaults, with
    /// convergence 10x looser on the coarse scan (its pose only seeds the fine stage).
    pub fn params(&self) -> RegistrationParams {
        let defaults = RegistrationParams::default();
        let loosen = if self.coarse { 10.0 } else { 1.0 };
        RegistrationParams {
            max_correspondence_distance: self.max_pair_dist,
            max_iterations: self.max_iterations,
            rotation_eps: defaults.rotation_eps * loosen,
            translation_eps: defaults.translation_eps * loosen,
            // The fine stage's pose is the one reported, with its covariance.
            gradient_cluster_m: (!self.coarse).then_some(SANDWICH_CLUSTER_M),
            ..defaults
        }
    }
}

/// The outcome of [`localize_scan`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localization {
    /// The adopted pose `T_map_sensor`; the prediction when `lost`.
    pub pose: Pose,
    /// Status, fitness, covariance.
    pub health: ScanHealth,
}

/// Runs registrations through `register` and keeps count.
struct Runner<'a, E, F: FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>> {
    register: F,
    params: &'a TrackingParams,
    fine: Stage,
    registrations: u32,
    iterations: u32,
}

impl<E, F: FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>> Runner<'_, E, F> {
    fn run(&mut self, start: &Pose, stage: &Stage) -> Result<Option<RegistrationResult>, E> {
        let result = (self.register)(start, stage)?;
        self.registrations += 1;
        self.iterations += result.as_ref().map_or(0, |r| r.iterations as u32);
        Ok(result)
    }

    /// Coarse iterations: the coarse scan, pairs up to `coarse-pair-dist` (at least the
    /// request's distance).
    fn coarse_stage(&self) -> Stage {
        Stage {
            coarse: true,
            max_pair_dist: self.params.coarse_pair_dist.max(self.fine.max_pair_dist),
            max_iterations: self.params.coarse_iterations,
        }
    }

    /// Coarse iterations from `start` (when `coarse` is set), then fine ones.
    fn coarse_to_fine(
        &mut self,
        start: &Pose,
        coarse: bool,
    ) -> Result<Option<RegistrationResult>, E> {
        let mut from = *start;
        if coarse {
            let stage = self.coarse_stage();
            if let Some(r) = self.run(start, &stage)? {
                from = r.pose;
            }
        }
        let fine = self.fine;
        self.run(&from, &fine)
    }
}

/// Localizes one scan from `prediction` (`T_map_sensor`) with the checks and retry
/// ladder of docs/DESIGN.md#tracking. `register(start, stage)` runs one registration
/// (e.g. GICP over a map server's cov2cov pairings) and returns `None` when it found no
/// correspondences. `fine` holds the request's pairing distance and iteration limit.
///
/// 1. Coarse iterations from the prediction (`coarse-first`), then fine ones. The
///    result is adopted when it pairs at least `ok-inlier-ratio` of the scan, not much
///    less than expected (`fitness-drop`), and its correction is within the expected
///    bound: `ok`, or `degraded` when degenerate or unconverged.
/// 2. Otherwise, or when the coarse iterations did not settle (no fine iterations are
///    spent on a start that poor), the ladder: without `coarse-first`, coarse then fine
///    iterations from the prediction; then every yaw hypothesis around the prediction
///    (and where the coarse iterations stopped) is scored by one coarse linearization,
///    and the best is registered coarse to fine.
/// 3. The best-fitting registration is taken. It is `lost` (no pose adopted) when it
///    pairs less than `lost-inlier-ratio`, much less than expected, or when a
///    disagreeing registration fits within `ambiguity-margin` of it. A correction
///    beyond the bound is adopted (`degraded`) only when the wider search confirmed
///    it: the scan then pairs at least `ok-inlier-ratio` and as well as expected (an
///    expectation is needed), else the scan is `lost`.
pub fn localize_scan<E>(
    prediction: &Pose,
    expected: &Expectation,
    fine: Stage,
    params: &TrackingParams,
    register: impl FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>,
) -> Result<Localization, E> {
    let mut runner = Runner {
        register,
        params,
        fine,
        registrations: 0,
        iterations: 0,
    };
    let correction =
        |r: &RegistrationResult| point_displacement(prediction, &r.pose, CORRECTION_RANGE_M);
    let max_correction = expected.max_correction;
    let plausible = |r: &RegistrationResult| max_correction.is_none_or(|m| correction(r) <= m);
    let fits = |r: &RegistrationResult| {
        let inliers = r.fitness.inlier_ratio;
        inliers >= params.ok_inlier_ratio
            && expected
                .inlier_ratio
                .is_none_or(|e| inliers >= e * (1.0 - params.fitness_drop))
    };

    let coarse = if params.coarse_first {
        let stage = runner.coarse_stage();
        runner.run(prediction, &stage)?
    } else {
        None
    };
    let settled = !params.coarse_first || coarse.as_ref().is_some_and(|r| r.converged);
    let mut candidates: Vec<RegistrationResult> = Vec::new();
    if settled {
        let start = coarse.as_ref().map_or(*prediction, |r| r.pose);
        if let Some(r) = runner.run(&start, &fine)? {
            if fits(&r) && plausible(&r) {
                let health = adopted(&r, Reasons::NONE, correction(&r), &runner);
                return Ok(Localization {
                    pose: r.pose,
                    health,
                });
            }
            candidates.push(r);
        }
    }
    if !params.coarse_first
        && let Some(r) = runner.coarse_to_fine(prediction, true)?
    {
        candidates.push(r);
    }
    if !candidates.iter().any(|c| fits(c) && plausible(c)) {
        let stopped = coarse.filter(|_| !settled).map(|r| r.pose);
        if let Some(r) = best_hypothesis(&mut runner, prediction, stopped)? {
            candidates.push(r);
        }
    }
    Ok(decide(prediction, expected, &candidates, &runner))
}

/// Scores every yaw hypothesis around `prediction` but the prediction itself, and
/// `stopped` (where unsettled coarse iterations ended), by one coarse linearization
/// (its inlier ratio at the fine pairing distance), and registers coarse to fine from
/// the best.
fn best_hypothesis<E, F>(
    runner: &mut Runner<'_, E, F>,
    prediction: &Pose,
    stopped: Option<Pose>,
) -> Result<Option<RegistrationResult>, E>
where
    F: FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>,
{
    let params = runner.params;
    let score_stage = Stage {
        coarse: true,
        max_pair_dist: runner.fine.max_pair_dist,
        max_iterations: 1,
    };
    let starts = yaw_hypotheses(prediction, params.yaw_step_deg, params.yaw_max_deg)
        .into_iter()
        .skip(1)
        .chain(stopped);
    let mut best: Option<(f64, Pose)> = None;
    for start in starts {
        if let Some(r) = runner.run(&start, &score_stage)?
            && best.is_none_or(|(score, _)| r.fitness.inlier_ratio > score)
        {
            best = Some((r.fitness.inlier_ratio, start));
        }
    }
    match best {
        Some((_, start)) => runner.coarse_to_fine(&start, true),
        None => Ok(None),
    }
}

/// The health of an adopted registration: `ok` unless degenerate, unconverged or
/// flagged by `reasons`.
fn adopted<E, F>(
    result: &RegistrationResult,
    mut reasons: Reasons,
    correction: f64,
    runner: &Runner<'_, E, F>,
) -> ScanHealth
where
    F: FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>,
{
    if result.degenerate {
        reasons.insert(Reasons::DEGENERATE);
    }
    if !result.converged {
        reasons.insert(Reasons::NOT_CONVERGED);
    }
    if result.fitness.inlier_ratio < runner.params.ok_inlier_ratio {
        reasons.insert(Reasons::LOW_FITNESS);
    }
    let covariance = pose_covariance(result);
    if covariance.is_none() {
        reasons.insert(Reasons::SINGULAR);
    }
    let marginal = Reasons::DEGENERATE
        | Reasons::NOT_CONVERGED
        | Reasons::LOW_FITNESS
        | Reasons::IMPLAUSIBLE
        | Reasons::SINGULAR;
    let status = if reasons.0 & marginal.0 == 0 {
        TrackingStatus::Ok
    } else {
        TrackingStatus::Degraded
    };
    ScanHealth {
        status,
        reasons,
        inlier_ratio: result.fitness.inlier_ratio,
        rmse: result.fitness.rmse,
        constraint: result.constraint,
        degenerate: result.degenerate,
        covariance,
        correction,
        registrations: runner.registrations,
        iterations: runner.iterations,
        converged: result.converged,
    }
}

/// The verdict of the ladder over its candidate registrations.
fn decide<E, F>(
    prediction: &Pose,
    expected: &Expectation,
    candidates: &[RegistrationResult],
    runner: &Runner<'_, E, F>,
) -> Localization
where
    F: FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>,
{
    let params = runner.params;
    let lost = |health: ScanHealth| Localization {
        pose: *prediction,
        health: ScanHealth {
            status: TrackingStatus::Lost,
            ..health
        },
    };
    let Some(best) = candidates
        .iter()
        .max_by(|a, b| a.fitness.inlier_ratio.total_cmp(&b.fitness.inlier_ratio))
    else {
        return lost(ScanHealth::no_fit(runner.registrations, runner.iterations));
    };
    let agree = |a: &Pose, b: &Pose| {
        translation_distance(a, b) <= params.agree_translation
            && rotation_distance(a, b).to_degrees() <= params.agree_rotation_deg
    };
    let best_pose = best.pose;
    let correction = point_displacement(prediction, &best_pose, CORRECTION_RANGE_M);
    let mut reasons = Reasons::RETRIED;
    let ambiguous = candidates.iter().any(|c| {
        !agree(&c.pose, &best_pose)
            && c.fitness.inlier_ratio + params.ambiguity_margin >= best.fitness.inlier_ratio
    });
    let implausible = expected.max_correction.is_some_and(|m| correction > m);
    let inliers = best.fitness.inlier_ratio;
    if inliers < params.lost_inlier_ratio {
        reasons.insert(Reasons::NO_FIT);
    }
    if expected
        .inlier_ratio
        .is_some_and(|e| inliers < e * (1.0 - params.fitness_drop))
    {
        reasons.insert(Reasons::FITNESS_DROP);
    }
    if ambiguous {
        reasons.insert(Reasons::AMBIGUOUS);
    }
    if implausible {
        reasons.insert(Reasons::IMPLAUSIBLE);
    }
    // A correction beyond the bound is adopted only when the scan then fits as well
    // as the scans before it (and nothing else fits as well).
    let verified = expected.inlier_ratio.is_some()
        && inliers >= params.ok_inlier_ratio
        && !reasons.contains(Reasons::FITNESS_DROP)
        && !ambiguous;
    let rejected = reasons.0 & (Reasons::NO_FIT | Reasons::FITNESS_DROP | Reasons::AMBIGUOUS).0
        != 0
        || (implausible && !verified);
    let health = adopted(best, reasons, correction, runner);
    if rejected {
        return lost(health);
    }
    Localization {
        pose: best_pose,
        health,
    }
}
