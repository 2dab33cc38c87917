//! The normal equations of a pose graph in a fixed sparse pattern (lower triangle,
//! 6x6 blocks), refilled each iteration and factorized by faer's sparse Cholesky with
//! the symbolic analysis (block AMD ordering, elimination tree) done once.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use faer::{Conj, Mat, Par, Side};
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
    /// Fill-reducing order of the scalar unknowns: AMD on the 6x6-block graph,
    /// expanded, so supernodes follow the blocks (and AMD runs on 36x fewer entries).
    forward: Vec<usize>,
    inverse: Vec<usize>,
}

impl Pattern {
    fn new(slot_pairs: &[[Option<usize>; 2]], free: usize) -> Result<Self, GraphError> {
        // Below-diagonal neighbours of each block column, sorted.
        let mut below: Vec<Vec<usize>> = vec![Vec::new(); free];
        for pair in slot_pairs {
            if let [Some(a), Some(b)] = *pair {
                below[a.min(b)].push(a.max(b));
            }
        }
        for rows in &mut below {
            rows.sort_unstable();
            rows.dedup();
        }
        let (mut col_ptr, mut row_idx) = (vec![0usize], Vec::new());
        for (c, rows) in below.iter().enumerate() {
            for j in 0..6 {
                row_idx.extend(c * 6 + j..c * 6 + 6);
                row_idx.extend(rows.iter().flat_map(|&r| r * 6..r * 6 + 6));
                col_ptr.push(row_idx.len());
            }
        }
        let n = free * 6;
        let values = vec![0.0; row_idx.len()];
        let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr.clone(), None, row_idx);
        let matrix = SparseColMat::new(symbolic, values);
        let diagonal = (0..free)
            .map(|c| std::array::from_fn(|j| col_ptr[c * 6 + j]))
            .collect();
        let off_diagonal = slot_pairs
            .iter()
            .map(|pair| match *pair {
                [Some(a), Some(b)] => {
                    let (hi, lo) = (a.max(b), a.min(b));
                    let k = below[lo].binary_search(&hi).expect("recorded above");
                    Some(std::array::from_fn(|j| {
                        col_ptr[lo * 6 + j] + (6 - j) + 6 * k
                    }))
                }
                _ => None,
            })
            .collect();
        let (forward, inverse) = block_ordering(&below)?;
        Ok(Self {
            matrix,
            diagonal,
            off_diagonal,
            forward,
            inverse,
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

/// AMD on the block graph, expanded to the six unknowns of each block.
fn block_ordering(below: &[Vec<usize>]) -> Result<(Vec<usize>, Vec<usize>), GraphError> {
    let free = below.len();
    let (mut col_ptr, mut row_idx) = (vec![0usize], Vec::new());
    for (c, rows) in below.iter().enumerate() {
        row_idx.push(c);
        row_idx.extend(rows);
        col_ptr.push(row_idx.len());
    }
    let nnz = row_idx.len();
    let blocks = SymbolicSparseColMat::new_checked(free, free, col_ptr, None, row_idx);
    let (mut perm, mut perm_inv) = (vec![0usize; free], vec![0usize; free]);
    let mut memory = MemBuffer::new(amd::order_scratch::<usize>(free, nnz));
    amd::order(
        &mut perm,
        &mut perm_inv,
        blocks.as_ref(),
        amd::Control::default(),
        MemStack::new(&mut memory),
    )
    .map_err(|e| GraphError::Singular(format!("ordering failed: {e:?}")))?;
    let expand = |p: &[usize]| (0..free * 6).map(|k| p[k / 6] * 6 + k % 6).collect();
    Ok((expand(&perm), expand(&perm_inv)))
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
    let n = free * 6;
    let symbolic = factorize_symbolic_cholesky(
        pattern.matrix.symbolic(),
        Side::Lower,
        SymmetricOrdering::Custom(PermRef::new_checked(&pattern.forward, &pattern.inverse, n)),
        Default::default(),
    )
    .map_err(|e| GraphError::Singular(format!("{e:?}")))?;
    let mut factor = vec![0.0; symbolic.len_val()];
    let mut memory = MemBuffer::new(
        symbolic
            .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
            .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq)),
    );
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
        // Levenberg-Marquardt retries a rejected step with more damping: it keeps the
        // undamped values and the poses to go back to; Gauss-Newton needs neither.
        let damped = params.optimizer == Optimizer::LevenbergMarquardt;
        let undamped = damped.then(|| pattern.matrix.val().to_vec());
        let mut accepted = false;
        for _ in 0..if damped { 10 } else { 1 } {
            if let Some(undamped) = &undamped {
                let values = pattern.matrix.val_mut();
                values.copy_from_slice(undamped);
                for &start in pattern.diagonal.iter().flatten() {
                    values[start] += lambda;
                }
            }
            let llt = symbolic
                .factorize_numeric_llt(
                    &mut factor,
                    pattern.matrix.as_ref(),
                    Side::Lower,
                    Default::default(),
                    Par::Seq,
                    MemStack::new(&mut memory),
                    Default::default(),
                )
                .map_err(|e| GraphError::Singular(format!("{e:?}")))?;
            let mut step = Mat::<f64>::from_fn(n, 1, |r, _| -gradient[r]);
            llt.solve_in_place_with_conj(
                Conj::No,
                step.as_mut(),
                Par::Seq,
                MemStack::new(&mut memory),
            );
            let before = damped.then(|| graph.poses.clone());
            for (i, slot) in slots.iter().enumerate() {
                if let Some(s) = slot {
                    let d = Vector6::from_fn(|r, _| step[(s * 6 + r, 0)]);
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
