//! The plane cost, its gradient and Gauss-Newton blocks from cluster statistics alone,
//! and Levenberg-Marquardt over every pose (docs/DESIGN.md#joint-refinement).
//!
//! A plane's cost is the sum of squared distances of all its points to their best common
//! plane: the smallest eigenvalue of the merged scatter. With the plane's normal `u` and
//! offset held (the offset follows the points), its Gauss-Newton Hessian over the
//! observers' right perturbations is `D_i` on the diagonal minus `b_i b_j^T / N`
//! everywhere (the offset eliminated), and everything is a closed form in each scan's
//! cluster (count, mean, scatter in its own frame).

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use rayon::prelude::*;

use super::planes::{Cluster, Plane};
use super::{Prior, RefineParams};
use crate::pose_graph::{exp, linearize_edge, log};
use crate::sparse_blocks::{BlockError, BlockSystem};
use kfmap_geometry::eigen::sorted_symmetric_eigen;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::RobustKernel;

/// Planes per parallel chunk: sums in fixed chunks do not depend on the thread count.
const CHUNK: usize = 256;
/// Planes whose blocks are held at once (bounds the linearization's memory: about 400 B
/// per observation).
const BATCH: usize = 8192;

/// What one plane set's solve did.
pub(crate) struct LmOutcome {
    /// Steps taken (accepted or not).
    pub iterations: usize,
    /// Whitened cost before and after.
    pub cost: (f64, f64),
}

/// The plane's observers moved to the map, and their union.
fn placed(plane: &Plane, poses: &[Pose]) -> (Vec<Cluster>, Cluster) {
    let moved: Vec<Cluster> = plane
        .observers
        .iter()
        .map(|(s, c)| c.moved(&poses[*s]))
        .collect();
    let all = Cluster::merged(moved.iter());
    (moved, all)
}

/// The plane's whitened robust cost and its weight (the kernel's slope over sigma^2):
/// `N rho(c / (N sigma^2))`, `c` the smallest eigenvalue of the merged scatter.
fn robust(c: f64, n: f64, sigma: f64, kernel: &RobustKernel) -> (f64, f64) {
    let s2 = sigma * sigma;
    let e2 = c.max(0.0) / (n * s2);
    (n * kernel.rho(e2), kernel.weight(e2) / s2)
}

/// The total whitened cost: planes plus odometry priors.
pub(crate) fn total_cost(
    planes: &[Plane],
    priors: &[Prior],
    poses: &[Pose],
    params: &RefineParams,
) -> f64 {
    let chunks: Vec<f64> = planes
        .par_chunks(CHUNK)
        .map(|chunk| {
            chunk
                .iter()
                .map(|plane| {
                    let (_, all) = placed(plane, poses);
                    let c = sorted_symmetric_eigen(&all.scatter).values[0];
                    robust(c, all.n, params.point_sigma, &params.kernel).0
                })
                .sum::<f64>()
        })
        .collect();
    chunks.iter().sum::<f64>() + prior_cost(priors, poses)
}

fn prior_cost(priors: &[Prior], poses: &[Pose]) -> f64 {
    priors
        .iter()
        .map(|p| {
            let e = log(&(p.measurement.inverse() * poses[p.from].inverse() * poses[p.to]));
            e.dot(&(p.information * e))
        })
        .sum()
}

/// One observer's share of a plane, in its own frame's right perturbation
/// `T exp(omega, v)`: half the gradient of the plane's cost, `D_i` and `b_i`.
pub(crate) struct ObserverBlocks {
    pub scan: usize,
    pub gradient: Vector6<f64>,
    pub d: Matrix6<f64>,
    pub b: Vector6<f64>,
}

/// The plane's blocks at `poses`, scaled by its robust weight, and its point count.
pub(crate) fn plane_blocks(
    plane: &Plane,
    poses: &[Pose],
    params: &RefineParams,
) -> (Vec<ObserverBlocks>, f64) {
    let (moved, all) = placed(plane, poses);
    let eigen = sorted_symmetric_eigen(&all.scatter);
    let u: Vector3<f64> = eigen.vectors.column(0).into_owned();
    let (_, weight) = robust(eigen.values[0], all.n, params.point_sigma, &params.kernel);
    let blocks = plane
        .observers
        .iter()
        .zip(&moved)
        .map(|((scan, local), world)| {
            let pose = &poses[*scan];
            // The normal in the scan's frame; points' residuals are w.q + offset.
            let w = pose.rotation.inverse() * u;
            let (n, m) = (local.n, local.mean);
            let offset = u.dot(&(world.mean - all.mean)) - w.dot(&m);
            let second = local.scatter + m * m.transpose() * n;
            let wx = w.cross_matrix();
            let mut gradient = Vector6::zeros();
            gradient
                .fixed_rows_mut::<3>(0)
                .copy_from(&(second * w + m * (offset * n)).cross(&w));
            gradient
                .fixed_rows_mut::<3>(3)
                .copy_from(&(w * (n * (w.dot(&m) + offset))));
            let mut d = Matrix6::zeros();
            d.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(wx * second * wx.transpose()));
            let top_right: Matrix3<f64> = -(wx * m) * w.transpose() * n;
            d.fixed_view_mut::<3, 3>(0, 3).copy_from(&top_right);
            d.fixed_view_mut::<3, 3>(3, 0)
                .copy_from(&top_right.transpose());
            d.fixed_view_mut::<3, 3>(3, 3)
                .copy_from(&(w * w.transpose() * n));
            let mut b = Vector6::zeros();
            b.fixed_rows_mut::<3>(0).copy_from(&(m.cross(&w) * n));
            b.fixed_rows_mut::<3>(3).copy_from(&(w * n));
            ObserverBlocks {
                scan: *scan,
                gradient: gradient * weight,
                d: d * weight,
                b: b * weight.sqrt(),
            }
        })
        .collect();
    (blocks, all.n)
}

/// Levenberg-Marquardt over every pose but scan 0's, the planes held. `Err` when the
/// block system cannot be set up (the poses are then untouched).
pub(crate) fn levenberg_marquardt(
    planes: &[Plane],
    priors: &[Prior],
    poses: &mut [Pose],
    params: &RefineParams,
    mut progress: impl FnMut(usize),
) -> Result<LmOutcome, BlockError> {
    let start = total_cost(planes, priors, poses, params);
    let mut outcome = LmOutcome {
        iterations: 0,
        cost: (start, start),
    };
    let free = poses.len() - 1;
    if free == 0 {
        return Ok(outcome);
    }
    // Scan s > 0 is unknown s - 1; scan 0 is the gauge.
    let slot = |s: usize| s.checked_sub(1);
    let pairs = planes
        .iter()
        .flat_map(|p| {
            let scans: Vec<usize> = p.observers.iter().filter_map(|(s, _)| slot(*s)).collect();
            let pairs: Vec<(usize, usize)> = (0..scans.len())
                .flat_map(|a| (a + 1..scans.len()).map(move |b| (a, b)))
                .map(|(a, b)| (scans[a], scans[b]))
                .collect();
            pairs
        })
        .chain(
            priors
                .iter()
                .filter_map(|p| Some((slot(p.from)?, slot(p.to)?))),
        );
    let mut system = BlockSystem::new(free, pairs)?;
    let mut cost = start;
    let mut mu = 1e-4;
    for _ in 0..params.max_iterations {
        outcome.iterations += 1;
        progress(outcome.iterations);
        let gradient = normal_equations(&mut system, planes, priors, poses, params);
        let undamped = system.values().to_vec();
        let mut accepted = None;
        for _ in 0..8 {
            system.set_values(&undamped);
            // Marquardt's scaling: rotations and translations differ in units.
            system.damp(|d| mu * d + 1e-9);
            let rhs: Vec<f64> = gradient.iter().map(|g| -g).collect();
            let step = match system.solve(&rhs) {
                Ok(step) => step,
                // Too little damping for a weakly held pose: damp more.
                Err(BlockError::NotPositiveDefinite { .. }) => {
                    mu *= 10.0;
                    continue;
                }
                Err(e) => return Err(e),
            };
            let trial: Vec<Pose> = poses
                .iter()
                .enumerate()
                .map(|(s, pose)| match slot(s) {
                    Some(k) => pose * exp(&Vector6::from_fn(|r, _| step[k * 6 + r])),
                    None => *pose,
                })
                .collect();
            let trial_cost = total_cost(planes, priors, &trial, params);
            if trial_cost < cost {
                accepted = Some((trial, trial_cost));
                mu = (mu / 3.0).max(1e-9);
                break;
            }
            mu *= 8.0;
        }
        let Some((trial, trial_cost)) = accepted else {
            break;
        };
        poses.copy_from_slice(&trial);
        let drop = (cost - trial_cost) / cost.max(f64::MIN_POSITIVE);
        cost = trial_cost;
        if drop < params.relative_cost_tol {
            break;
        }
    }
    outcome.cost.1 = cost;
    Ok(outcome)
}

/// Adds planes' blocks (each with its point count) to `system` and `gradient`.
fn add_plane_blocks(
    system: &mut BlockSystem,
    gradient: &mut [f64],
    blocks: &[(Vec<ObserverBlocks>, f64)],
) {
    let slot = |s: usize| s.checked_sub(1);
    for (observers, n) in blocks {
        for (a, oa) in observers.iter().enumerate() {
            let Some(i) = slot(oa.scan) else { continue };
            for r in 0..6 {
                gradient[i * 6 + r] += oa.gradient[r];
            }
            system.add_diagonal(i, &(oa.d - oa.b * oa.b.transpose() / *n));
            for ob in &observers[a + 1..] {
                let Some(j) = slot(ob.scan) else { continue };
                system.add_off_diagonal(i, j, &(-oa.b * ob.b.transpose() / *n));
            }
        }
    }
}

/// Fills `system` with the Gauss-Newton Hessian at `poses` and returns the gradient (both
/// halved, as the pose graph's).
fn normal_equations(
    system: &mut BlockSystem,
    planes: &[Plane],
    priors: &[Prior],
    poses: &[Pose],
    params: &RefineParams,
) -> Vec<f64> {
    let slot = |s: usize| s.checked_sub(1);
    let mut gradient = vec![0.0; system.dim()];
    system.clear();
    // Computed in parallel, added in plane order, a bounded batch of planes at a time.
    for batch in planes.chunks(BATCH) {
        let blocks: Vec<(Vec<ObserverBlocks>, f64)> = batch
            .par_iter()
            .with_min_len(CHUNK)
            .map(|p| plane_blocks(p, poses, params))
            .collect();
        add_plane_blocks(system, &mut gradient, &blocks);
    }
    for p in priors {
        let e = linearize_edge(
            &poses[p.from],
            &poses[p.to],
            &p.measurement,
            &p.information,
            RobustKernel::None,
        );
        let ends = [slot(p.from), slot(p.to)];
        for ((end, h), b) in ends.iter().zip(&e.h).zip(&e.b) {
            if let Some(s) = *end {
                system.add_diagonal(s, h);
                for r in 0..6 {
                    gradient[s * 6 + r] += b[r];
                }
            }
        }
        if let [Some(a), Some(b)] = ends {
            system.add_off_diagonal(a, b, &e.h[2]);
        }
    }
    gradient
}
