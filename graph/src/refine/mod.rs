//! Joint refinement of every scan's pose by plane bundle adjustment
//! (docs/DESIGN.md#joint-refinement): the scans' points are cut into planes by adaptive
//! voxels; each plane keeps, per scan that sees it, the cluster statistics of that scan's
//! points (count, mean, scatter), and every pose is solved together so that each plane is
//! as thin as the data allows (the smallest eigenvalue of the merged scatter, as BALM's
//! point clusters). Levenberg-Marquardt on the block-sparse normal equations; planes are
//! found again at the new poses a few times.

mod consistency;
mod planes;
mod solve;
#[cfg(test)]
mod tests;

use std::time::Instant;

use nalgebra::Matrix6;
use serde::{Deserialize, Serialize};

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::options::{InvalidOption, ensure, ensure_distance, ensure_ratio};
use kfmap_geometry::registration::RobustKernel;

pub use consistency::{Consistency, consistency};

/// The refinement's settings (`bake.toml`'s `[build.refine]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct RefineParams {
    /// Refine the built poses at all.
    pub enabled: bool,
    /// Each scan's points are thinned on a voxel grid of this edge first, metres.
    pub point_voxel: f64,
    /// ...and to at most this many points (an even stride through the rest).
    pub max_points_per_scan: usize,
    /// Edge of the root voxels the planes are cut from, metres.
    pub voxel_size: f64,
    /// How often a root voxel that is not planar may be split into eight.
    pub max_depth: u32,
    /// A plane needs at least this many points...
    pub min_points: usize,
    /// ...seen from at least this many scans...
    pub min_observers: usize,
    /// ...its smallest eigenvalue at most this share of the middle one...
    pub plane_ratio: f64,
    /// ...and its points at most this RMS distance from it, metres.
    pub max_thickness: f64,
    /// A scan whose own points lie further than this from the plane (in the mean) does
    /// not observe it (the far side of a thin wall, another surface), metres.
    pub max_offset: f64,
    /// Scans kept per plane, evenly spread over the run (bounds the cost of planes seen
    /// from everywhere).
    pub max_observers: usize,
    /// A scan counts at most this many points in a plane (a scan close to a wall does
    /// not outweigh the rest).
    pub max_observer_points: usize,
    /// The points' noise, metres: the plane cost is measured in it.
    pub point_sigma: f64,
    /// Down-weights planes whose points lie far from a common plane (on the RMS
    /// distance in point sigmas).
    pub kernel: RobustKernel,
    /// Times the planes are found again at the new poses.
    pub outer_iterations: usize,
    /// Levenberg-Marquardt steps per plane set.
    pub max_iterations: usize,
    /// Stop when a step lowers the cost by less than this share.
    pub relative_cost_tol: f64,
    /// Consecutive scans keep their odometry motion with this rotation sigma, degrees
    /// (weakly: it holds directions no plane constrains)...
    pub prior_sigma_deg: f64,
    /// ...and this translation sigma, metres.
    pub prior_sigma: f64,
    /// A scan with fewer planes than this is reported weak.
    pub min_planes_per_scan: usize,
    /// If any scan would move further than this, metres, plus `max_move_per_100m` per
    /// 100 m of path from scan 0, the refinement is refused and the poses are kept (a
    /// wrong association, not a correction).
    pub max_move: f64,
    /// The move allowed grows by this many metres per 100 m of path from scan 0 (the
    /// gauge): odometry drift accumulates along an open drive, so correcting it moves far
    /// scans further than near ones.
    pub max_move_per_100m: f64,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            enabled: true,
            point_voxel: 0.1,
            max_points_per_scan: 20_000,
            voxel_size: 2.0,
            max_depth: 2,
            min_points: 15,
            min_observers: 2,
            plane_ratio: 1.0 / 16.0,
            max_thickness: 0.05,
            max_offset: 0.3,
            max_observers: 48,
            max_observer_points: 10_000,
            point_sigma: 0.02,
            kernel: RobustKernel::Cauchy { delta: 3.0 },
            outer_iterations: 3,
            max_iterations: 10,
            relative_cost_tol: 1e-4,
            prior_sigma_deg: 2.0,
            prior_sigma: 0.05,
            min_planes_per_scan: 20,
            max_move: 0.5,
            max_move_per_100m: 0.5,
        }
    }
}

impl RefineParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure_distance("point-voxel", self.point_voxel)?;
        ensure(
            self.max_points_per_scan >= 100,
            "max-points-per-scan",
            self.max_points_per_scan,
            "at least 100",
        )?;
        ensure_distance("voxel-size", self.voxel_size)?;
        ensure(self.max_depth <= 6, "max-depth", self.max_depth, "0 to 6")?;
        ensure(
            self.min_points >= 4,
            "min-points",
            self.min_points,
            "at least 4",
        )?;
        ensure(
            self.min_observers >= 2,
            "min-observers",
            self.min_observers,
            "at least 2",
        )?;
        ensure_ratio("plane-ratio", self.plane_ratio)?;
        ensure_distance("max-thickness", self.max_thickness)?;
        ensure_distance("max-offset", self.max_offset)?;
        ensure(
            self.max_observers >= self.min_observers,
            "max-observers",
            self.max_observers,
            "at least min-observers",
        )?;
        ensure(
            self.max_observer_points >= 1,
            "max-observer-points",
            self.max_observer_points,
            "at least 1",
        )?;
        ensure_distance("point-sigma", self.point_sigma)?;
        if let Some(delta) = self.kernel.delta() {
            ensure(
                delta.is_finite() && delta > 0.0,
                "kernel",
                delta,
                "a kernel with a finite delta > 0",
            )?;
        }
        ensure(
            self.outer_iterations >= 1,
            "outer-iterations",
            self.outer_iterations,
            "at least 1",
        )?;
        ensure(
            self.max_iterations >= 1,
            "max-iterations",
            self.max_iterations,
            "at least 1",
        )?;
        ensure(
            self.relative_cost_tol.is_finite() && self.relative_cost_tol >= 0.0,
            "relative-cost-tol",
            self.relative_cost_tol,
            "a finite share >= 0",
        )?;
        ensure(
            self.prior_sigma_deg.is_finite() && self.prior_sigma_deg >= 0.0,
            "prior-sigma-deg",
            self.prior_sigma_deg,
            "finite degrees >= 0 (0: no priors)",
        )?;
        ensure(
            self.prior_sigma.is_finite() && self.prior_sigma >= 0.0,
            "prior-sigma",
            self.prior_sigma,
            "a finite distance >= 0 m (0: no priors)",
        )?;
        ensure_distance("max-move", self.max_move)?;
        ensure(
            self.max_move_per_100m.is_finite() && self.max_move_per_100m >= 0.0,
            "max-move-per-100m",
            self.max_move_per_100m,
            "a finite distance >= 0 m (0: max-move everywhere)",
        )
    }

    /// The move allowed to a scan `path` metres along the input poses from scan 0.
    fn allowed_move(&self, path: f64) -> f64 {
        self.max_move + self.max_move_per_100m * path / 100.0
    }

    /// The information of an odometry prior (`None`: priors are off).
    fn prior_information(&self) -> Option<Matrix6<f64>> {
        let (r, t) = (self.prior_sigma_deg.to_radians(), self.prior_sigma);
        (r > 0.0 && t > 0.0).then(|| {
            let (wr, wt) = (1.0 / (r * r), 1.0 / (t * t));
            Matrix6::from_diagonal(&nalgebra::Vector6::new(wr, wr, wr, wt, wt, wt))
        })
    }
}

/// One scan to refine: its points in its own frame, and its pose (`T_map_cloud`).
#[derive(Debug, Clone, Copy)]
pub struct RefineScan<'a> {
    /// Points, the scan's frame (deskewed, thinned).
    pub points: &'a [[f32; 3]],
    /// `T_map_cloud` before refining.
    pub pose: Pose,
}

/// What the refinement did.
#[derive(Debug, Clone, Default)]
pub struct RefineReport {
    /// Why the result was refused (the input poses kept); `None`: the refined poses
    /// were kept.
    pub refused: Option<String>,
    /// Planes of the last plane set.
    pub planes: usize,
    /// Scan-plane observations of the last plane set.
    pub observations: usize,
    /// Plane sets (re-voxelizations) solved.
    pub outer_iterations: usize,
    /// Levenberg-Marquardt steps over all plane sets.
    pub iterations: usize,
    /// Whitened cost at the start and at the end of the first plane set, and of the last.
    pub cost_first: (f64, f64),
    /// As `cost_first`, for the last plane set.
    pub cost_last: (f64, f64),
    /// Largest distance a scan moved, metres.
    pub largest_move: f64,
    /// The scan that used the largest share of its allowed move (`max-move` plus
    /// `max-move-per-100m` of its path from scan 0), its move and its allowance, metres.
    pub tightest_move: Option<TightestMove>,
    /// Scans moved more than 0.1 m.
    pub moved_scans: Vec<usize>,
    /// Scans in fewer than `min-planes-per-scan` planes (held by their priors).
    pub weak_scans: Vec<usize>,
    /// Map consistency at the input poses and at the result.
    pub consistency_before: Consistency,
    /// As `consistency_before`, at the refined poses (or the input, when refused).
    pub consistency_after: Consistency,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// The scan whose move came nearest its allowance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TightestMove {
    /// The scan's index.
    pub scan: usize,
    /// How far it moved, metres.
    pub moved: f64,
    /// How far it could move: `max-move` plus `max-move-per-100m` of its path from scan 0.
    pub allowed: f64,
}

/// The scan nearest its move allowance, for `moves` of scans along `input` poses.
fn tightest_move(input: &[Pose], moves: &[f64], params: &RefineParams) -> Option<TightestMove> {
    let mut path = 0.0;
    let mut tightest: Option<TightestMove> = None;
    for (scan, &moved) in moves.iter().enumerate() {
        if scan > 0 {
            path += (input[scan].translation.vector - input[scan - 1].translation.vector).norm();
        }
        let candidate = TightestMove {
            scan,
            moved,
            allowed: params.allowed_move(path),
        };
        if tightest.is_none_or(|t| moved / candidate.allowed > t.moved / t.allowed) {
            tightest = Some(candidate);
        }
    }
    tightest
}

/// Why a refinement that ran as `report` says is refused, if it is: the solve could not
/// run, nothing to refine, a scan moved too far, or the map got less consistent.
fn verdict(
    report: &RefineReport,
    scans: usize,
    unsolvable: Option<&crate::sparse_blocks::BlockError>,
    params: &RefineParams,
) -> Option<String> {
    let too_far = report.tightest_move.filter(|t| t.moved > t.allowed);
    if let Some(e) = unsolvable {
        Some(format!("the plane system could not be solved: {e}"))
    } else if scans < 2 {
        Some("fewer than two scans: nothing to refine".into())
    } else if report.outer_iterations == 0 {
        Some("no planes seen from two scans".into())
    } else if let Some(t) = too_far {
        Some(format!(
            "scan {} would move {:.2} m, more than its {:.2} m (max-move {} m plus {} m per \
             100 m of path from scan 0)",
            t.scan, t.moved, t.allowed, params.max_move, params.max_move_per_100m
        ))
    } else if report.consistency_after.mean_spread > report.consistency_before.mean_spread {
        Some("the map got less consistent".into())
    } else {
        None
    }
}

impl RefineReport {
    /// The refined poses were kept (not refused).
    pub fn accepted(&self) -> bool {
        self.refused.is_none()
    }
}

/// A relative-pose prior between two scans (`T_from^-1 T_to ~ measurement`).
#[derive(Debug, Clone, Copy)]
struct Prior {
    from: usize,
    to: usize,
    measurement: Pose,
    information: Matrix6<f64>,
}

/// Refines the poses of `scans` together; scan 0 stays fixed (it defines the map frame).
/// `odometry` (one pose per scan, any frame, or empty) gives consecutive scans weak
/// priors on their relative motion. `measured` names the scans the consistency figures
/// are taken over (e.g. the keyframes). Returns the poses to use (the input ones when
/// the result is refused) and the report; `progress(done, total)` counts LM steps.
pub fn refine_poses(
    scans: &[RefineScan<'_>],
    odometry: &[Pose],
    measured: &[usize],
    params: &RefineParams,
    mut progress: impl FnMut(usize, usize),
) -> (Vec<Pose>, RefineReport) {
    let started = Instant::now();
    let clouds: Vec<&[[f32; 3]]> = scans.iter().map(|s| s.points).collect();
    let input: Vec<Pose> = scans.iter().map(|s| s.pose).collect();
    let mut report = RefineReport {
        consistency_before: consistency(&clouds, &input, measured),
        ..Default::default()
    };
    let priors: Vec<Prior> = match params.prior_information() {
        Some(information) if odometry.len() == scans.len() => (1..scans.len())
            .map(|i| Prior {
                from: i - 1,
                to: i,
                measurement: odometry[i - 1].inverse() * odometry[i],
                information,
            })
            .collect(),
        _ => Vec::new(),
    };
    let mut poses = input.clone();
    let total = params.outer_iterations * params.max_iterations;
    // Why the solve could not run, when it could not.
    let mut unsolvable = None;
    for outer in 0..params.outer_iterations {
        let planes = planes::find_planes(&clouds, &poses, params);
        report.planes = planes.len();
        report.observations = planes.iter().map(|p| p.observers.len()).sum();
        if planes.is_empty() {
            break;
        }
        let before = poses.clone();
        let lm = match solve::levenberg_marquardt(&planes, &priors, &mut poses, params, |k| {
            progress(outer * params.max_iterations + k, total)
        }) {
            Ok(lm) => lm,
            Err(e) => {
                unsolvable = Some(e);
                break;
            }
        };
        report.outer_iterations += 1;
        report.iterations += lm.iterations;
        if outer == 0 {
            report.cost_first = lm.cost;
            report.weak_scans = planes::weak_scans(&planes, scans.len(), params);
        }
        report.cost_last = lm.cost;
        let shift = before
            .iter()
            .zip(&poses)
            .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
            .fold(0.0, f64::max);
        // A plane set that barely moves anything would find the same planes again.
        if shift < 1e-3 {
            break;
        }
    }
    progress(total, total);
    let moves: Vec<f64> = input
        .iter()
        .zip(&poses)
        .map(|(a, b)| (a.translation.vector - b.translation.vector).norm())
        .collect();
    report.largest_move = moves.iter().copied().fold(0.0, f64::max);
    report.tightest_move = tightest_move(&input, &moves, params);
    report.moved_scans = (0..moves.len()).filter(|&i| moves[i] > 0.1).collect();
    report.consistency_after = consistency(&clouds, &poses, measured);
    report.refused = verdict(&report, scans.len(), unsolvable.as_ref(), params);
    if !report.accepted() {
        poses = input;
        report.consistency_after = report.consistency_before;
    }
    report.seconds = started.elapsed().as_secs_f64();
    (poses, report)
}
