//! What `kfmap inspect-cloud` reports about a cloud: extent, density, spacing and the
//! shape of its covariances, with timings.

use std::num::NonZeroUsize;
use std::time::Instant;

use serde::Serialize;

use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::spatial::{TreeError, build_tree};

/// Statistics of a cloud and of its per-point covariances.
#[derive(Debug, Clone, Serialize)]
pub struct CloudSummary {
    /// Number of points.
    pub points: usize,
    /// Smallest coordinate on each axis, metres.
    pub bbox_min: [f32; 3],
    /// Largest coordinate on each axis, metres.
    pub bbox_max: [f32; 3],
    /// Points per cubic metre of bounding box; `None` for a flat box.
    pub density_points_per_m3: Option<f64>,
    /// Median distance from a point to its nearest other point, metres.
    pub median_nn_spacing_m: Option<f64>,
    /// Fraction of points whose covariance is the isotropic fallback.
    pub fallback_fraction: f64,
    /// Mean planarity of the non-fallback neighbourhoods, in [0, 1].
    pub mean_planarity: Option<f64>,
    /// KD-tree build time, milliseconds.
    pub tree_ms: f64,
    /// Covariance estimation time, milliseconds.
    pub covariances_ms: f64,
    /// Threads used for covariance estimation.
    pub threads: usize,
}

/// Median spacing over an evenly strided sample of at most this many points.
const SPACING_SAMPLE: usize = 10_000;

/// Summarizes a non-empty cloud with finite points.
pub fn summarize(cloud: &PointCloud, options: &CovOptions) -> Result<CloudSummary, TreeError> {
    let bbox = cloud.bounding_box().ok_or(TreeError::Empty)?;
    let started = Instant::now();
    let tree = build_tree(&cloud.points)?;
    let tree_ms = started.elapsed().as_secs_f64() * 1e3;
    let started = Instant::now();
    let covs = estimate_covariances(&cloud.points, options);
    let covariances_ms = started.elapsed().as_secs_f64() * 1e3;

    let volume = bbox.volume();
    let stride = cloud.len().div_ceil(SPACING_SAMPLE).max(1);
    let two = NonZeroUsize::new(2).expect("2 > 0");
    let mut spacings: Vec<f64> = cloud
        .points
        .iter()
        .step_by(stride)
        .filter_map(|q| {
            // The second is the nearest other point (the first is q itself).
            tree.view()
                .nearest_n(q, two)
                .get(1)
                .map(|&(_, dist_sq)| dist_sq)
        })
        .map(|d2| (d2 as f64).sqrt())
        .collect();
    spacings.sort_by(f64::total_cmp);
    Ok(CloudSummary {
        points: cloud.len(),
        bbox_min: bbox.min,
        bbox_max: bbox.max,
        density_points_per_m3: (volume > 0.0).then(|| cloud.len() as f64 / volume),
        median_nn_spacing_m: spacings.get(spacings.len() / 2).copied(),
        fallback_fraction: covs.fallback_count as f64 / cloud.len() as f64,
        mean_planarity: covs.mean_planarity,
        tree_ms,
        covariances_ms,
        threads: rayon::current_num_threads(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_summary_matches_closed_form() {
        // 10 x 10 x 2 grid with 0.5 m spacing: box 4.5 x 4.5 x 0.5 m, spacing 0.5 m.
        let points: Vec<[f32; 3]> = (0..200)
            .map(|i| {
                [
                    (i % 10) as f32 * 0.5,
                    (i / 10 % 10) as f32 * 0.5,
                    (i / 100) as f32 * 0.5,
                ]
            })
            .collect();
        let s = summarize(&PointCloud::from_points(points), &CovOptions::default()).unwrap();
        assert_eq!(s.points, 200);
        assert_eq!(s.bbox_max, [4.5, 4.5, 0.5]);
        assert!((s.density_points_per_m3.unwrap() - 200.0 / (4.5 * 4.5 * 0.5)).abs() < 1e-9);
        assert!((s.median_nn_spacing_m.unwrap() - 0.5).abs() < 1e-6);
        // Within r = 1 m every point has at least 5 neighbours (itself + 4 at 0.5 m).
        assert_eq!(s.fallback_fraction, 0.0);
    }

    #[test]
    fn collinear_points_have_zero_planarity() {
        // On a line e0 = e1 = 0, so 2 (e1 - e0) / (e0 + e1 + e2) = 0.
        let points: Vec<[f32; 3]> = (0..50)
            .map(|i| [i as f32 * 0.1, 2.0 * i as f32 * 0.1, 1.0])
            .collect();
        let s = summarize(&PointCloud::from_points(points), &CovOptions::default()).unwrap();
        assert!(
            s.mean_planarity.unwrap().abs() < 1e-6,
            "{:?}",
            s.mean_planarity
        );
    }

    #[test]
    fn empty_cloud_is_an_error() {
        assert!(summarize(&PointCloud::default(), &CovOptions::default()).is_err());
    }
}
