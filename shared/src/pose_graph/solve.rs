//! The normal equations of a pose graph in a fixed sparse pattern (lower triangle,
//! 6x6 blocks), refilled each iteration and factorized by faer's sparse Cholesky with
//! the symbolic analysis (AMD ordering, elimination tree) done once.

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use nalgebra::{Matrix6, Vector6};
use rayon::prelude::*;

use super::se3::{adjoint, exp, log, right_jacobian_inverse};
use super::{GraphError, GraphParams, GraphReport, PoseGraph};
use crate::registration::Optimizer;

/// One edge's contribution, computed in parallel and added in edge order.
struct EdgeBlocks {
    /// Free slots of the edge's vertices.
    slots: [Option<usize>; 2],
    /// `J_i^T W J_i`, `J_j^T W J_j`, `J_i^T W J_j`.
    h: [Matrix6<f64>; 3],
    /// `J_i^T W e`, `J_j^T W e`.
    b: [Vector6<f64>; 2],
}

/// Where each block lives in the matrix's value array: the start of each of its six
/// columns (rows within a block column are contiguous).
struct Pattern {
    matrix: SparseColMat<usize, f64>,
    /// Per free slot: the diagonal block (lower triangle; column j starts at row j).
    diagonal: Vec<[usize; 6]>,
    /// Per edge with both ends free: the off-diagonal block below the diagonal.
    off_diagonal: Vec<Option<[usize; 6]>>,
}

impl Pattern {
    fn new(slot_pairs: &[[Option<usize>; 2]], free: usize) -> Result<Self, GraphError> {
        let n = free * 6;
        let mut triplets = Vec::new();
        for s in 0..free {
            for c in 0..6 {
                for r in c..6 {
                    triplets.push(Triplet::new(s * 6 + r, s * 6 + c, 0.0));
                }
            }
        }
        for pair in slot_pairs {
            if let [Some(a), Some(b)] = *pair {
                let (hi, lo) = (a.max(b), a.min(b));
                for c in 0..6 {
                    for r in 0..6 {
                        triplets.push(Triplet::new(hi * 6 + r, lo * 6 + c, 0.0));
                    }
                }
            }
        }
        let matrix = SparseColMat::try_new_from_triplets(n, n, &triplets)
            .map_err(|e| GraphError::Singular(format!("cannot build the matrix: {e:?}")))?;
        let (col_ptr, row_idx) = (matrix.symbolic().col_ptr(), matrix.symbolic().row_idx());
        let position = |row: usize, col: usize| {
            let range = col_ptr[col]..col_ptr[col + 1];
            range.start
                + row_idx[range]
                    .binary_search(&row)
                    .expect("every block entry is in the pattern")
        };
        let diagonal = (0..free)
            .map(|s| std::array::from_fn(|c| position(s * 6 + c, s * 6 + c)))
            .collect();
        let off_diagonal = slot_pairs
            .iter()
            .map(|pair| match *pair {
                [Some(a), Some(b)] => {
                    let (hi, lo) = (a.max(b), a.min(b));
                    Some(std::array::from_fn(|c| position(hi * 6, lo * 6 + c)))
                }
                _ => None,
            })
            .collect();
        Ok(Self {
            matrix,
            diagonal,
            off_diagonal,
        })
    }

    /// Adds `block` (6x6) at the diagonal of `slot` (lower triangle only).
    fn add_diagonal(values: &mut [f64], starts: &[usize; 6], block: &Matrix6<f64>) {
        for c in 0..6 {
            for r in c..6 {
                values[starts[c] + r - c] += block[(r, c)];
            }
        }
    }

    fn add_block(values: &mut [f64], starts: &[usize; 6], block: &Matrix6<f64>) {
        for c in 0..6 {
            for r in 0..6 {
                values[starts[c] + r] += block[(r, c)];
            }
        }
    }
}

fn edge_blocks(graph: &PoseGraph, slots: &[Option<usize>]) -> Vec<EdgeBlocks> {
    graph
        .edges
        .par_iter()
        .map(|e| {
            let (i, j) = (graph.index[&e.from], graph.index[&e.to]);
            let (xi, xj) = (&graph.poses[i], &graph.poses[j]);
            let error = log(&(e.measurement.inverse() * xi.inverse() * xj));
            let weight = e.kernel.weight(error.dot(&(e.information * error)));
            let w = e.information * weight;
            let jj = right_jacobian_inverse(&error);
            let ji = -jj * adjoint(&(xj.inverse() * xi));
            EdgeBlocks {
                slots: [slots[i], slots[j]],
                h: [
                    ji.transpose() * w * ji,
                    jj.transpose() * w * jj,
                    ji.transpose() * w * jj,
                ],
                b: [ji.transpose() * w * error, jj.transpose() * w * error],
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
    let slot_pairs: Vec<[Option<usize>; 2]> = graph
        .edges
        .iter()
        .map(|e| [slots[graph.index[&e.from]], slots[graph.index[&e.to]]])
        .collect();
    let mut pattern = Pattern::new(&slot_pairs, free)?;
    let symbolic = SymbolicLlt::try_new(pattern.matrix.symbolic(), Side::Lower)
        .map_err(|e| GraphError::Singular(format!("{e:?}")))?;
    let mut error = initial_error;
    let mut lambda = 1e-5;
    report.converged = false;
    for _ in 0..params.max_iterations {
        report.iterations += 1;
        let blocks = edge_blocks(graph, &slots);
        let mut gradient = vec![0.0; free * 6];
        let values = pattern.matrix.val_mut();
        values.fill(0.0);
        for (k, e) in blocks.iter().enumerate() {
            for end in 0..2 {
                if let Some(s) = e.slots[end] {
                    Pattern::add_diagonal(values, &pattern.diagonal[s], &e.h[end]);
                    for r in 0..6 {
                        gradient[s * 6 + r] += e.b[end][r];
                    }
                }
            }
            if let (Some(starts), [Some(a), Some(b)]) = (&pattern.off_diagonal[k], e.slots) {
                // Stored below the diagonal: block (max, min) of H_ij = J_i^T W J_j.
                let block = if a > b { e.h[2] } else { e.h[2].transpose() };
                Pattern::add_block(values, starts, &block);
            }
        }
        let undamped: Vec<f64> = pattern.matrix.val().to_vec();
        let mut accepted = false;
        for _ in 0..if params.optimizer == Optimizer::LevenbergMarquardt {
            10
        } else {
            1
        } {
            let values = pattern.matrix.val_mut();
            values.copy_from_slice(&undamped);
            if params.optimizer == Optimizer::LevenbergMarquardt {
                for starts in &pattern.diagonal {
                    for &start in starts {
                        values[start] += lambda;
                    }
                }
            }
            let llt =
                Llt::try_new_with_symbolic(symbolic.clone(), pattern.matrix.as_ref(), Side::Lower)
                    .map_err(|e| GraphError::Singular(format!("{e:?}")))?;
            let mut step = Mat::<f64>::from_fn(free * 6, 1, |r, _| -gradient[r]);
            llt.solve_in_place(step.as_mut());
            let before = graph.poses.clone();
            for (i, slot) in slots.iter().enumerate() {
                if let Some(s) = slot {
                    let d = Vector6::from_fn(|r, _| step[(s * 6 + r, 0)]);
                    graph.poses[i] *= exp(&d);
                }
            }
            let new_error = graph.error();
            if params.optimizer == Optimizer::GaussNewton || new_error <= error {
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
            graph.poses = before;
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
