//! How well a map's scans agree with each other, for any set of poses
//! (docs/DESIGN.md#joint-refinement): over a fixed grid of 1 m cubes (not the
//! refinement's own voxels, so it grades what it did not choose), the surfaces that at
//! least three scans each see as a plane of their own.

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use super::planes::{Cluster, keyed_points, runs};
use kfmap_geometry::eigen::sorted_symmetric_eigen;
use kfmap_geometry::geometry::Pose;

/// Edge of the grid's cubes, metres.
const CUBE_M: f64 = 1.0;
/// A scan sees a surface in a cube with at least this many points...
const MIN_POINTS: usize = 10;
/// ...lying on a plane of its own (smallest eigenvalue at most this share of the middle
/// one): judged per scan, so a misaligned map does not fail the test it is graded by.
const OWN_PLANE_RATIO: f64 = 0.1;
/// A surface counts when this many scans see it.
const MIN_SCANS: usize = 3;

/// Map consistency figures, metres.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Consistency {
    /// Surfaces (1 m cubes) seen as planes by at least three scans.
    pub surfaces: usize,
    /// Mean thickness: RMS distance of all the scans' points in a cube to their common
    /// plane.
    pub mean_thickness: f64,
    /// Mean spread: the part of the thickness the scans' disagreement makes (RMS offset
    /// of each scan's own points from the common plane, weighted by their count).
    pub mean_spread: f64,
}

/// The consistency of the scans `measured` (indices into `clouds`, points in each scan's
/// frame) at `poses`.
pub fn consistency(clouds: &[&[[f32; 3]]], poses: &[Pose], measured: &[usize]) -> Consistency {
    let keyed = keyed_points(clouds, poses, measured, CUBE_M);
    let figures: Vec<(f64, f64)> = runs(&keyed, |e| e.0)
        .into_par_iter()
        .filter_map(|range| {
            let cube = &keyed[range];
            let seen: Vec<Cluster> = runs(cube, |e| e.1)
                .into_iter()
                .filter(|scan| scan.len() >= MIN_POINTS)
                .map(|run| {
                    let points: Vec<Vector3<f64>> = cube[run]
                        .iter()
                        .map(|&(_, scan, k)| {
                            let p = clouds[scan as usize][k as usize];
                            let local =
                                nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                            poses[scan as usize].transform_point(&local).coords
                        })
                        .collect();
                    Cluster::of(&points)
                })
                .filter(|own| {
                    let values = sorted_symmetric_eigen(&own.scatter).values;
                    values[0] <= OWN_PLANE_RATIO * values[1]
                })
                .collect();
            (seen.len() >= MIN_SCANS).then(|| {
                let all = Cluster::merged(seen.iter());
                let eigen = sorted_symmetric_eigen(&all.scatter);
                let u = eigen.vectors.column(0);
                let spread: f64 = seen
                    .iter()
                    .map(|c| c.n * u.dot(&(c.mean - all.mean)).powi(2))
                    .sum();
                (
                    (eigen.values[0].max(0.0) / all.n).sqrt(),
                    (spread / all.n).sqrt(),
                )
            })
        })
        .collect();
    let count = figures.len();
    let mean = |f: fn(&(f64, f64)) -> f64| {
        if count == 0 {
            0.0
        } else {
            figures.iter().map(f).sum::<f64>() / count as f64
        }
    };
    Consistency {
        surfaces: count,
        mean_thickness: mean(|f| f.0),
        mean_spread: mean(|f| f.1),
    }
}
