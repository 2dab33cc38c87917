//! The normal equations of a pose graph in a fixed sparse pattern (lower triangle,
//! 6x6 blocks), refilled each iteration and factorized by faer's sparse Cholesky with
//! the symbolic analysis (block AMD ordering, elimination tree) done once.

use nalgebra::{Matrix6, Vector6};
use rayon::prelude::*;

use super::{GraphError, GraphParams, GraphReport, PoseGraph};
use crate::sparse_blocks::BlockSystem;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::registration::{Optimizer, RobustKernel};
use kfmap_geometry::se3::{adjoint, exp, log, right_jacobian_inverse};

/// One edge's contribution, computed in parallel and added in edge order.
struct EdgeBlocks {
    /// Free slots of the edge's vertices.
    slots: [Option<usize>; 2],
    /// The linearized edge.
    linear: EdgeLinearization,
}

/// A relative-pose edge `Z ~ X_i^-1 X_j` linearized at `X_i`, `X_j` (right perturbations).
pub(crate) struct EdgeLinearization {
    /// `J_i^T W J_i`, `J_j^T W J_j`, `J_i^T W J_j`.
    pub h: [Matrix6<f64>; 3],
    /// `J_i^T W e`, `J_j^T W e`.
    pub b: [Vector6<f64>; 2],
}

/// Linearizes the edge `measurement` with `information` (robustly weighted by `kernel`)
/// between `xi` and `xj`.
pub(crate) fn linearize_edge(
    xi: &Pose,
    xj: &Pose,
    measurement: &Pose,
    information: &Matrix6<f64>,
    kernel: RobustKernel,
) -> EdgeLinearization {
    let error = log(&(measurement.inverse() * xi.inverse() * xj));
    let weight = kernel.weight(error.dot(&(information * error)));
    let w = information * weight;
    let jj = right_jacobian_inverse(&error);
    let ji = -jj * adjoint(&(xj.inverse() * xi));
    EdgeLinearization {
        h: [
            ji.transpose() * w * ji,
            jj.transpose() * w * jj,
            ji.transpose() * w * jj,
        ],
        b: [ji.transpose() * w * error, jj.transpose() * w * error],
    }
}

fn edge_blocks(graph: &PoseGraph, slots: &[Option<usize>]) -> Vec<EdgeBlocks> {
    graph
        .edges
        .par_iter()
        .map(|e| {
            let (i, j) = (graph.index[&e.from], graph.index[&e.to]);
            EdgeBlocks {
                slots: [slots[i], slots[j]],
                linear: linearize_edge(
                    &graph.poses[i],
                    &graph.poses[j],
                    &e.measurement,
                    &e.information,
                    e.kernel,
                ),
            }
        })
        .collect()
}

pub(super) fn optimize(
    graph: &mut PoseGraph,
    params: &GraphParams,
) -> Result<GraphReport, GraphError> {
    let fixed = params
        .fixed
        .unwrap_or(*graph.ids.first().ok_or(GraphError::Empty)?);
    let fixed_index = *graph.index.get(&fixed).ok_or(GraphError::UnknownVertex {
        from: fixed,
        to: fixed,
        missing: fixed,
    })?;
    let mut next = 0;
    let slots: Vec<Option<usize>> = (0..graph.len())
        .map(|i| {
            (i != fixed_index).then(|| {
                next += 1;
                next - 1
            })
        })
        .collect();
    let free = next;
    let initial_error = graph.error();
    let mut report = GraphReport {
        initial_error,
        final_error: initial_error,
        errors: Vec::new(),
        iterations: 0,
        converged: true,
    };
    if free == 0 || graph.edges.is_empty() {
        return Ok(report);
    }
    let pairs = graph.edges.iter().filter_map(|e| {
        match (slots[graph.index[&e.from]], slots[graph.index[&e.to]]) {
            (Some(a), Some(b)) => Some((a, b)),
            _ => None,
        }
    });
    let mut system = BlockSystem::new(free, pairs)?;
    let mut error = initial_error;
    let mut lambda = 1e-5;
    report.converged = false;
    for _ in 0..params.max_iterations {
        report.iterations += 1;
        let blocks = edge_blocks(graph, &slots);
        let mut gradient = vec![0.0; free * 6];
        system.clear();
        for e in &blocks {
            let (h, b) = (&e.linear.h, &e.linear.b);
            for end in 0..2 {
                if let Some(s) = e.slots[end] {
                    system.add_diagonal(s, &h[end]);
                    for r in 0..6 {
                        gradient[s * 6 + r] += b[end][r];
                    }
                }
            }
            if let [Some(a), Some(b)] = e.slots {
                system.add_off_diagonal(a, b, &h[2]);
            }
        }
        // Levenberg-Marquardt retries a rejected step with more damping: it keeps the
        // undamped values and the poses to go back to; Gauss-Newton needs neither.
        let damped = params.optimizer == Optimizer::LevenbergMarquardt;
        let undamped = damped.then(|| system.values().to_vec());
        let mut accepted = false;
        for _ in 0..if damped { 10 } else { 1 } {
            if let Some(undamped) = &undamped {
                system.set_values(undamped);
                system.damp(|_| lambda);
            }
            let rhs: Vec<f64> = gradient.iter().map(|g| -g).collect();
            let step = system.solve(&rhs)?;
            let before = damped.then(|| graph.poses.clone());
            for (i, slot) in slots.iter().enumerate() {
                if let Some(s) = slot {
                    let d = Vector6::from_fn(|r, _| step[s * 6 + r]);
                    graph.poses[i] *= exp(&d);
                }
            }
            let new_error = graph.error();
            if !damped || new_error <= error {
                lambda = (lambda / 10.0).max(1e-12);
                accepted = true;
                let decrease = (error - new_error) / error.max(f64::MIN_POSITIVE);
                error = new_error;
                report.errors.push(error);
                if decrease.abs() < params.relative_error_tol || error < params.absolute_error_tol {
                    report.converged = true;
                }
                break;
            }
            graph.poses = before.expect("kept when damped");
            lambda *= 10.0;
        }
        if !accepted || report.converged {
            report.converged |= !accepted;
            break;
        }
    }
    report.final_error = error;
    Ok(report)
}
