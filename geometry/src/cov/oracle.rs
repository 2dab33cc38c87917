//! The covariance oracle: the specification of docs/DESIGN.md#covariances written as
//! plainly as possible. Compiled for this crate's tests and, with the `oracles`
//! feature, for the tests of the crates above (the map's cov2cov pairings).

use nalgebra::{Matrix3, Vector3};

use super::{CovCenter, CovOptions, ISOTROPIC};
use crate::geometry::{PackedSym3, pack_sym3};

/// Oracle: the specification of docs/DESIGN.md#covariances written as plainly as possible,
/// with a linear scan instead of a tree.
pub fn brute_force(points: &[[f32; 3]], options: &CovOptions) -> Vec<PackedSym3> {
    let as_f64 = |p: &[f32; 3]| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
    let n = points.len();
    let k = options.k_correspondences_for_cov.min(n);
    let r2 = options.max_distance_for_cov.powi(2);
    points
        .iter()
        .map(|q| {
            let qv = as_f64(q);
            let mut by_distance: Vec<(f64, usize)> = points
                .iter()
                .enumerate()
                .map(|(i, p)| ((as_f64(p) - qv).norm_squared(), i))
                .collect();
            by_distance.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let found: Vec<Vector3<f64>> = by_distance[..k]
                .iter()
                .filter(|(d, _)| *d < r2)
                .map(|&(_, i)| as_f64(&points[i]))
                .collect();
            if n < 3 || found.len() < options.min_correspondences_for_cov.min(k) {
                return ISOTROPIC;
            }
            let mean = found.iter().sum::<Vector3<f64>>() / found.len() as f64;
            let c = if options.cov_center == CovCenter::Mean {
                mean
            } else {
                qv
            };
            let mut s = Matrix3::zeros();
            for p in &found {
                s += (p - c) * (p - c).transpose();
            }
            s /= found.len() as f64;
            let eig = s.symmetric_eigen();
            let mut idx = [0, 1, 2];
            idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
            if options.max_plane_deviation_for_cov > 0.0 {
                let mut sm = Matrix3::zeros();
                for p in &found {
                    sm += (p - mean) * (p - mean).transpose();
                }
                let e2 = sm.symmetric_eigen();
                let imin = (0..3)
                    .min_by(|&a, &b| e2.eigenvalues[a].total_cmp(&e2.eigenvalues[b]))
                    .unwrap();
                let normal = e2.eigenvectors.column(imin);
                if found
                    .iter()
                    .any(|p| (p - mean).dot(&normal).abs() > options.max_plane_deviation_for_cov)
                {
                    return ISOTROPIC;
                }
            }
            let smax = eig.eigenvalues[idx[2]];
            let mut out = Matrix3::zeros();
            for (rank, &i) in idx.iter().enumerate() {
                let v = eig.eigenvectors.column(i);
                let value = if options.lambda > 0.0 {
                    if rank == 0 { options.lambda } else { 1.0 }
                } else {
                    eig.eigenvalues[i].max(options.lambda.abs() * smax)
                };
                out += v * v.transpose() * value;
            }
            pack_sym3(&out)
        })
        .collect()
}
