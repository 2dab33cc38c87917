//! Per-point covariance estimation (docs/DESIGN.md#covariances), as MOLA's
//! `KeyframePointCloudMap` with its defects fixed: never a zero matrix, optional
//! mean or query centring, plane regularization or eigenvalue flooring.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::eigen::{smallest_eigenvector, sorted_symmetric_eigen, symmetric_eigenvalues};
use crate::geometry::{PackedSym3, pack_sym3, to_vec3};
use crate::neighbourhoods::{Found, map_neighbourhoods};
use crate::options::{InvalidOption, ensure};

/// Where the neighbourhood scatter is centred.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CovCenter {
    /// On the neighbourhood mean (a true covariance).
    Mean,
    /// On the query point itself (MOLA's choice).
    Query,
}

/// Options of per-point covariance estimation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct CovOptions {
    /// Neighbours searched per point, the point itself included (k).
    pub k_correspondences_for_cov: usize,
    /// Fewer neighbours than `min(this, k)` give the isotropic fallback.
    pub min_correspondences_for_cov: usize,
    /// Neighbours must lie strictly closer than this, metres.
    pub max_distance_for_cov: f64,
    /// Positive: plane regularization, eigenvalues (1, 1, lambda) in m^2. Negative: keep
    /// the real eigenvalues, floor the two smaller at |lambda| times the largest.
    pub lambda: f64,
    /// Centre of the neighbourhood scatter.
    pub cov_center: CovCenter,
    /// When positive and a neighbour lies farther than this (metres) from the fitted
    /// plane, the isotropic fallback is used. 0 disables the gate.
    pub max_plane_deviation_for_cov: f64,
}

impl Default for CovOptions {
    fn default() -> Self {
        Self {
            k_correspondences_for_cov: 20,
            min_correspondences_for_cov: 5,
            max_distance_for_cov: 1.0,
            lambda: 1e-3,
            cov_center: CovCenter::Mean,
            max_plane_deviation_for_cov: 0.0,
        }
    }
}

impl CovOptions {
    /// Checks every option; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let k = self.k_correspondences_for_cov;
        ensure(
            (3..=1024).contains(&k),
            "k-correspondences-for-cov",
            k,
            "an integer in [3, 1024]",
        )?;
        let min = self.min_correspondences_for_cov;
        ensure(
            (3..=k).contains(&min),
            "min-correspondences-for-cov",
            min,
            &format!("an integer in [3, k-correspondences-for-cov = {k}]"),
        )?;
        let r = self.max_distance_for_cov;
        ensure(
            r.is_finite() && r > 0.0,
            "max-distance-for-cov",
            r,
            "a finite distance > 0 m",
        )?;
        let l = self.lambda;
        ensure(
            l.is_finite() && l != 0.0,
            "lambda",
            l,
            "a finite non-zero number (> 0 regularizes, < 0 floors eigenvalues)",
        )?;
        let d = self.max_plane_deviation_for_cov;
        ensure(
            d.is_finite() && d >= 0.0,
            "max-plane-deviation-for-cov",
            d,
            "a finite distance >= 0 m (0 disables)",
        )
    }
}

/// Covariances of a cloud, one per point, plus how they were obtained.
#[derive(Debug, Clone, PartialEq)]
pub struct Covariances {
    /// Packed covariance of each point, m^2.
    pub values: Vec<PackedSym3>,
    /// Points that got the isotropic fallback (identity).
    pub fallback_count: usize,
    /// Mean planarity `2 (e1 - e0) / (e0 + e1 + e2)` of the non-fallback neighbourhoods.
    pub mean_planarity: Option<f64>,
}

/// The isotropic fallback, 1 m^2 on each axis.
pub const ISOTROPIC: PackedSym3 = [1.0, 0.0, 0.0, 1.0, 0.0, 1.0];

/// Result for one point: covariance and planarity, or `None` for the fallback.
type PointEstimate = Option<(PackedSym3, f64)>;

/// Estimates the covariance of every point of `points` (all-kNN, see
/// [`map_neighbourhoods`]). Runs on the current rayon pool; the output does not depend
/// on the thread count.
pub fn estimate_covariances(points: &[[f32; 3]], options: &CovOptions) -> Covariances {
    let k = options.k_correspondences_for_cov.min(points.len());
    let r = options.max_distance_for_cov;
    let estimates: Vec<PointEstimate> =
        map_neighbourhoods(points, k, (r * r) as f32, |i, found| {
            from_neighbours(points.len(), &points[i], found, options)
        });
    let fallback_count = estimates.iter().filter(|e| e.is_none()).count();
    let planar: Vec<f64> = estimates.iter().flatten().map(|&(_, p)| p).collect();
    let mean_planarity =
        (!planar.is_empty()).then(|| planar.iter().sum::<f64>() / planar.len() as f64);
    Covariances {
        values: estimates
            .into_iter()
            .map(|e| e.map_or(ISOTROPIC, |(c, _)| c))
            .collect(),
        fallback_count,
        mean_planarity,
    }
}

/// Steps 2-5 of docs/DESIGN.md#covariances on the `neighbours` found for `query` in a
/// cloud of `cloud_len` points.
fn from_neighbours(
    cloud_len: usize,
    query: &[f32; 3],
    neighbours: &[Found],
    options: &CovOptions,
) -> PointEstimate {
    let k = options.k_correspondences_for_cov.min(cloud_len);
    if cloud_len < 3 || neighbours.len() < options.min_correspondences_for_cov.min(k) {
        return None;
    }
    // One pass of moments about the query point: neighbours are within r of it, so
    // the centring correction loses no precision.
    let q = to_vec3(query);
    let mut sum = Vector3::zeros();
    let mut m = [0.0f64; 6]; // xx xy xz yy yz zz
    for nb in neighbours {
        let d = to_vec3(&nb.point) - q;
        sum += d;
        m[0] += d.x * d.x;
        m[1] += d.x * d.y;
        m[2] += d.x * d.z;
        m[3] += d.y * d.y;
        m[4] += d.y * d.z;
        m[5] += d.z * d.z;
    }
    let moments = Matrix3::new(m[0], m[1], m[2], m[1], m[3], m[4], m[2], m[4], m[5]);
    let count = neighbours.len() as f64;
    let mean_offset = sum / count;
    let about_mean = moments / count - mean_offset * mean_offset.transpose();
    let scatter = match options.cov_center {
        CovCenter::Mean => about_mean,
        CovCenter::Query => moments / count,
    };
    if options.max_plane_deviation_for_cov > 0.0 {
        let members = neighbours.iter().map(|nb| to_vec3(&nb.point) - q);
        if !fits_plane(
            members,
            &mean_offset,
            &about_mean,
            options.max_plane_deviation_for_cov,
        ) {
            return None;
        }
    }
    regularize(&scatter, options.lambda)
}

/// Step 4 of docs/DESIGN.md#covariances: plane regularization (`lambda > 0`) or eigenvalue
/// flooring (`lambda < 0`); `None` when the scatter is zero (coincident neighbours).
fn regularize(scatter: &Matrix3<f64>, lambda: f64) -> PointEstimate {
    let s = symmetric_eigenvalues(scatter);
    if s.z <= 0.0 {
        return None;
    }
    let planarity = (2.0 * (s.y - s.x) / (s.x + s.y + s.z)).clamp(0.0, 1.0);
    let cov = if lambda > 0.0 {
        // U diag(lambda, 1, 1) U^T = I - (1 - lambda) v0 v0^T: only the normal matters.
        let normal = smallest_eigenvector(scatter, &s).unwrap_or_else(|| {
            sorted_symmetric_eigen(scatter)
                .vectors
                .column(0)
                .into_owned()
        });
        Matrix3::identity() - normal * normal.transpose() * (1.0 - lambda)
    } else {
        let eig = sorted_symmetric_eigen(scatter);
        let e = eig.values;
        let floor = lambda.abs() * e.z;
        let floored = Vector3::new(e.x.max(floor), e.y.max(floor), e.z);
        eig.vectors * Matrix3::from_diagonal(&floored) * eig.vectors.transpose()
    };
    Some((pack_sym3(&cov), planarity))
}

/// True when every member lies within `max_deviation` metres of the least-squares
/// plane through the members (through their mean, normal to the smallest eigenvector).
fn fits_plane(
    members: impl Iterator<Item = Vector3<f64>>,
    mean: &Vector3<f64>,
    about_mean: &Matrix3<f64>,
    max_deviation: f64,
) -> bool {
    let normal = sorted_symmetric_eigen(about_mean)
        .vectors
        .column(0)
        .into_owned();
    members
        .into_iter()
        .all(|p| (p - mean).dot(&normal).abs() <= max_deviation)
}

#[cfg(any(test, feature = "oracles"))]
pub mod oracle;
#[cfg(test)]
mod tests;
