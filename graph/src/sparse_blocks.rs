//! Symmetric positive-definite systems in 6x6 blocks (one per pose), stored as the lower
//! triangle of a fixed sparse pattern, refilled each iteration and factorized by faer's
//! sparse Cholesky with the symbolic analysis (block AMD ordering, elimination tree) done
//! once. The pose graph and the joint refinement both solve their normal equations here.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use faer::{Conj, Mat, Par, Side};
use nalgebra::Matrix6;

/// Why a block system could not be set up or solved. Callers tell them apart: a matrix
/// that is not positive definite may be damped more; a failed set-up cannot be retried.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BlockError {
    /// The ordering or the symbolic analysis failed (faer's message: out of memory, an
    /// index overflow).
    #[error("the block system could not be set up: {0}")]
    Setup(String),
    /// The values are not positive definite: an unknown no constraint pins, or too
    /// little damping.
    #[error("the system is not positive definite (pivot {pivot})")]
    NotPositiveDefinite {
        /// The unknown whose pivot was not positive (in the ordered system).
        pivot: usize,
    },
}

/// A block-sparse symmetric system over `free` poses with a fixed pattern.
pub struct BlockSystem {
    matrix: SparseColMat<usize, f64>,
    /// Per block column: the start of each of its six columns in the value array (the
    /// diagonal block's column j starts at its row j).
    column_starts: Vec<[usize; 6]>,
    /// Per block column: the block rows below the diagonal, sorted.
    below: Vec<Vec<usize>>,
    symbolic: SymbolicCholesky<usize>,
    factor: Vec<f64>,
    memory: MemBuffer,
}

impl BlockSystem {
    /// The pattern of the diagonal blocks and of the off-diagonal blocks `pairs` names
    /// (either order; repeats are merged).
    pub fn new(
        free: usize,
        pairs: impl IntoIterator<Item = (usize, usize)>,
    ) -> Result<Self, BlockError> {
        let mut below: Vec<Vec<usize>> = vec![Vec::new(); free];
        for (a, b) in pairs {
            if a != b {
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
        let pattern = SymbolicSparseColMat::new_checked(n, n, col_ptr.clone(), None, row_idx);
        let matrix = SparseColMat::new(pattern, values);
        let column_starts = (0..free)
            .map(|c| std::array::from_fn(|j| col_ptr[c * 6 + j]))
            .collect();
        let (forward, inverse) = block_ordering(&below)?;
        let symbolic = factorize_symbolic_cholesky(
            matrix.symbolic(),
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&forward, &inverse, n)),
            Default::default(),
        )
        .map_err(|e| BlockError::Setup(format!("symbolic analysis: {e:?}")))?;
        let factor = vec![0.0; symbolic.len_val()];
        let memory = MemBuffer::new(
            symbolic
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
                .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq)),
        );
        Ok(Self {
            matrix,
            column_starts,
            below,
            symbolic,
            factor,
            memory,
        })
    }

    /// Unknowns: six per free pose.
    pub fn dim(&self) -> usize {
        self.column_starts.len() * 6
    }

    /// Sets every value to zero.
    pub fn clear(&mut self) {
        self.matrix.val_mut().fill(0.0);
    }

    /// The values (lower triangle, pattern order), e.g. to keep and restore them.
    pub fn values(&self) -> &[f64] {
        self.matrix.val()
    }

    /// Replaces the values with `values` (as [`BlockSystem::values`] gave them).
    pub fn set_values(&mut self, values: &[f64]) {
        self.matrix.val_mut().copy_from_slice(values);
    }

    /// Adds `block` to the diagonal block of pose `slot` (its lower triangle is read).
    pub fn add_diagonal(&mut self, slot: usize, block: &Matrix6<f64>) {
        let starts = self.column_starts[slot];
        let values = self.matrix.val_mut();
        for c in 0..6 {
            for r in c..6 {
                values[starts[c] + r - c] += block[(r, c)];
            }
        }
    }

    /// Adds `block` as the block at row `i`, column `j` (and its transpose at `j`, `i`);
    /// the pair must be in the pattern.
    pub fn add_off_diagonal(&mut self, i: usize, j: usize, block: &Matrix6<f64>) {
        let (lo, hi, stored) = if i > j {
            (j, i, *block)
        } else {
            (i, j, block.transpose())
        };
        let k = self.below[lo]
            .binary_search(&hi)
            .expect("the pair is in the pattern");
        let starts = self.column_starts[lo];
        let values = self.matrix.val_mut();
        for c in 0..6 {
            let start = starts[c] + (6 - c) + 6 * k;
            for r in 0..6 {
                values[start + r] += stored[(r, c)];
            }
        }
    }

    /// Adds `by(diagonal value)` to each diagonal value (damping).
    pub fn damp(&mut self, by: impl Fn(f64) -> f64) {
        let values = self.matrix.val_mut();
        for starts in &self.column_starts {
            for &s in starts {
                values[s] += by(values[s]);
            }
        }
    }

    /// Solves `A x = rhs` with the current values.
    pub fn solve(&mut self, rhs: &[f64]) -> Result<Vec<f64>, BlockError> {
        let llt = self
            .symbolic
            .factorize_numeric_llt(
                &mut self.factor,
                self.matrix.as_ref(),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut self.memory),
                Default::default(),
            )
            .map_err(|e| match e {
                faer::linalg::solvers::LltError::NonPositivePivot { index } => {
                    BlockError::NotPositiveDefinite { pivot: index }
                }
            })?;
        let mut x = Mat::<f64>::from_fn(rhs.len(), 1, |r, _| rhs[r]);
        llt.solve_in_place_with_conj(
            Conj::No,
            x.as_mut(),
            Par::Seq,
            MemStack::new(&mut self.memory),
        );
        Ok((0..rhs.len()).map(|r| x[(r, 0)]).collect())
    }
}

/// AMD on the block graph, expanded to the six unknowns of each block, so supernodes
/// follow the blocks (and AMD runs on 36x fewer entries).
fn block_ordering(below: &[Vec<usize>]) -> Result<(Vec<usize>, Vec<usize>), BlockError> {
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
    .map_err(|e| BlockError::Setup(format!("ordering: {e:?}")))?;
    let expand = |p: &[usize]| (0..free * 6).map(|k| p[k / 6] * 6 + k % 6).collect();
    Ok((expand(&perm), expand(&perm_inv)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    /// The sparse solve equals a dense solve of the same matrix (a chain plus one long
    /// pair, so the ordering matters).
    #[test]
    fn block_solve_equals_dense_solve() {
        let free = 5;
        let pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0)];
        let mut system = BlockSystem::new(free, pairs).unwrap();
        let mut dense = DMatrix::<f64>::zeros(30, 30);
        let value = |r: usize, c: usize| ((r * 7 + c * 13) % 11) as f64 * 0.1 - 0.5;
        for s in 0..free {
            let d = Matrix6::from_fn(|r, c| {
                if r == c {
                    20.0
                } else {
                    value(r.max(c), r.min(c))
                }
            });
            system.add_diagonal(s, &d);
            dense.view_mut((s * 6, s * 6), (6, 6)).copy_from(&d);
        }
        for &(i, j) in &pairs {
            let b = Matrix6::from_fn(|r, c| value(r + i, c + j));
            system.add_off_diagonal(i, j, &b);
            dense.view_mut((i * 6, j * 6), (6, 6)).copy_from(&b);
            dense
                .view_mut((j * 6, i * 6), (6, 6))
                .copy_from(&b.transpose());
        }
        let rhs: Vec<f64> = (0..30).map(|k| (k as f64).sin()).collect();
        let x = system.solve(&rhs).unwrap();
        let expected = dense
            .cholesky()
            .unwrap()
            .solve(&nalgebra::DVector::from_vec(rhs));
        for k in 0..30 {
            assert!(
                (x[k] - expected[k]).abs() < 1e-12,
                "{k}: {} {}",
                x[k],
                expected[k]
            );
        }
    }

    /// A pose nothing constrains (its block zero) is told apart from a failed set-up:
    /// `NotPositiveDefinite` at one of its six unknowns, which a damped solve can fix.
    #[test]
    fn an_unconstrained_pose_is_not_positive_definite() {
        let mut system = BlockSystem::new(3, [(0, 1)]).unwrap();
        system.add_diagonal(0, &(Matrix6::identity() * 2.0));
        system.add_diagonal(1, &(Matrix6::identity() * 2.0));
        let rhs = vec![1.0; 18];
        let error = system.solve(&rhs).unwrap_err();
        assert!(
            matches!(error, BlockError::NotPositiveDefinite { .. }),
            "{error:?}"
        );
        system.damp(|_| 1e-6);
        let x = system.solve(&rhs).unwrap();
        assert!(
            (x[0] - 0.5).abs() < 1e-6 && (x[12] - 1e6).abs() < 1e-3,
            "{x:?}"
        );
    }
}
