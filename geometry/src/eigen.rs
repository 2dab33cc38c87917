//! Eigen-decomposition of symmetric 3x3 matrices with a fixed (ascending) order.

use nalgebra::{Matrix3, Vector3};

/// Eigenvalues ascending and the matching unit eigenvectors as columns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SortedEigen3 {
    /// `e0 <= e1 <= e2`.
    pub values: Vector3<f64>,
    /// Column `i` is the eigenvector of `values[i]`.
    pub vectors: Matrix3<f64>,
}

/// Decomposes a symmetric matrix; eigenvalues come out ascending.
pub fn sorted_symmetric_eigen(m: &Matrix3<f64>) -> SortedEigen3 {
    let eig = m.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    SortedEigen3 {
        values: Vector3::from_fn(|i, _| eig.eigenvalues[order[i]]),
        vectors: Matrix3::from_fn(|r, c| eig.eigenvectors[(r, order[c])]),
    }
}

/// Eigenvalues `e0 <= e1 <= e2` of a symmetric matrix in closed form (the
/// trigonometric method); absolute error about 1e-8 of the matrix norm at worst.
pub fn symmetric_eigenvalues(m: &Matrix3<f64>) -> Vector3<f64> {
    let off = m[(0, 1)].powi(2) + m[(0, 2)].powi(2) + m[(1, 2)].powi(2);
    let q = m.trace() / 3.0;
    let diag = [m[(0, 0)] - q, m[(1, 1)] - q, m[(2, 2)] - q];
    let p2 = diag.iter().map(|d| d * d).sum::<f64>() + 2.0 * off;
    if p2 <= f64::MIN_POSITIVE {
        return Vector3::repeat(q);
    }
    let p = (p2 / 6.0).sqrt();
    let b = (m - Matrix3::from_diagonal_element(q)) / p;
    let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    Vector3::new(smallest, 3.0 * q - largest - smallest, largest)
}

/// Unit eigenvector of the smallest eigenvalue `e0` (from [`symmetric_eigenvalues`]),
/// by cross products of the rows of `m - e0 I`. `None` when `e0` is too close to `e1`
/// for that to be accurate (the caller then uses [`sorted_symmetric_eigen`]).
pub fn smallest_eigenvector(m: &Matrix3<f64>, values: &Vector3<f64>) -> Option<Vector3<f64>> {
    let shifted = m - Matrix3::from_diagonal_element(values.x);
    let rows = [
        shifted.row(0).transpose(),
        shifted.row(1).transpose(),
        shifted.row(2).transpose(),
    ];
    let candidates = [
        rows[0].cross(&rows[1]),
        rows[0].cross(&rows[2]),
        rows[1].cross(&rows[2]),
    ];
    let best = candidates
        .into_iter()
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    // |cross| ~ (e1 - e0)(e2 - e0) and |shifted|_F^2 ~ (e1 - e0)^2 + (e2 - e0)^2: the
    // ratio is about the relative gap, below 1e-3 the direction is not trustworthy.
    let scale = shifted.norm_squared();
    (best.norm() > 1e-3 * scale && scale > 0.0).then(|| best.normalize())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reconstructs_the_matrix_with_ascending_values() {
        let m = Matrix3::new(4.0, 1.0, 0.5, 1.0, 3.0, -0.2, 0.5, -0.2, 0.1);
        let e = sorted_symmetric_eigen(&m);
        assert!(e.values.x <= e.values.y && e.values.y <= e.values.z);
        let back = e.vectors * Matrix3::from_diagonal(&e.values) * e.vectors.transpose();
        assert!((back - m).norm() < 1e-12);
    }

    #[test]
    fn closed_form_agrees_with_iterative_solver() {
        // Random symmetric matrices, including plane-like ones with a tiny e0.
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for case in 0..2000 {
            let q =
                nalgebra::Rotation3::new(Vector3::new(next(), next(), next()) * 6.0).into_inner();
            let scale = if case % 2 == 0 { 1e-4 } else { 0.3 };
            let d = Vector3::new(scale * (next() + 0.5), 1.0 + next(), 2.0 + next());
            let m = q * Matrix3::from_diagonal(&d) * q.transpose();
            let want = sorted_symmetric_eigen(&m);
            let got = symmetric_eigenvalues(&m);
            assert!(
                (got - want.values).norm() < 1e-9,
                "{got} vs {}",
                want.values
            );
            let v = smallest_eigenvector(&m, &got).expect("well separated");
            assert!(v.dot(&want.vectors.column(0)).abs() > 1.0 - 1e-9);
        }
        // Degenerate e0 == e1: refused rather than guessed.
        let m = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 3.0));
        assert!(smallest_eigenvector(&m, &symmetric_eigenvalues(&m)).is_none());
        assert_eq!(
            symmetric_eigenvalues(&Matrix3::identity()),
            Vector3::repeat(1.0)
        );
    }
}
