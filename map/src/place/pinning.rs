//! Whether the scans pin a place (docs/DESIGN.md#tracking): what a scan's structure
//! shows of the map there, and what a slide of the distance `ok` promises along the
//! place's least constrained horizontal direction costs of it. A place along a
//! corridor-like stretch explains nearly as much as the right one but slides; a
//! look-alike that is itself a place (a courtyard's twin) pins as the right one does.
//! The tracker and the server's relocalization verdict measure it the same way, each
//! with its own nearest-neighbour queries.

use kfmap_geometry::geometry::Pose;
use nalgebra::{Matrix6, Point3, SymmetricEigen, Vector3};

use super::relocalize::{Ground, off_ground};

/// Columns of [`structure`]'s ground, metres.
const STRUCTURE_CELL_M: f64 = 1.0;
/// Fewest structure points a scan is compared on (else it is measured whole)...
const MIN_COMPARED_POINTS: usize = 50;
/// ... and most (thinned evenly beyond).
const MAX_COMPARED_POINTS: usize = 2000;
/// How far [`slide_loss`] slides a pose: the distance `ok` promises, metres.
pub const SLIDE_PROBE_M: f64 = 0.5;

/// `points`' structure: those (sensor frame) at least 1 m above their column's floor in
/// the map frame at `pose`, thinned evenly to at most 2000. Places are compared on
/// this: the ground is alike under every placement and would drown the difference (on
/// a courtyard's rotated twin the whole scan's shares differed by 0.007). A scan with
/// too little structure is taken whole.
pub fn structure(points: &[[f32; 3]], pose: &Pose) -> Vec<[f32; 3]> {
    let in_map: Vec<[f64; 3]> = points
        .iter()
        .map(|p| {
            let p = pose * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [p.x, p.y, p.z]
        })
        .collect();
    let off = off_ground(&in_map, STRUCTURE_CELL_M, Ground::Every);
    let mut kept: Vec<[f32; 3]> = points
        .iter()
        .zip(off)
        .filter_map(|(p, off)| off.then_some(*p))
        .collect();
    if kept.len() < MIN_COMPARED_POINTS {
        kept = points.to_vec();
    }
    let stride = kept.len().div_ceil(MAX_COMPARED_POINTS).max(1);
    kept.into_iter().step_by(stride).collect()
}

/// The horizontal direction (map frame, unit) along which `covariance` (sensor frame,
/// right perturbation, rotation first) is widest; `None` when it is not finite.
pub fn widest_horizontal(covariance: &Matrix6<f64>, pose: &Pose) -> Option<Vector3<f64>> {
    let rotation = pose.rotation.to_rotation_matrix();
    let in_map =
        rotation.matrix() * covariance.fixed_view::<3, 3>(3, 3) * rotation.matrix().transpose();
    let horizontal = in_map.fixed_view::<2, 2>(0, 0).into_owned();
    if !horizontal.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eigen = SymmetricEigen::new(horizontal);
    let widest = eigen.eigenvalues.imax();
    let v = eigen.eigenvectors.column(widest);
    Some(Vector3::new(v[0], v[1], 0.0))
}

/// How much of the share explained at `pose` (`here`) a slide of [`SLIDE_PROBE_M`]
/// along `covariance`'s widest horizontal direction loses, at the worse side
/// (`explained_at` measures a pose's share): near zero when the scan does not pin the
/// pose to that distance, below zero when a better fit lies beside it. `None` when the
/// covariance is not finite.
pub fn slide_loss<E>(
    pose: &Pose,
    covariance: &Matrix6<f64>,
    here: f64,
    mut explained_at: impl FnMut(&Pose) -> Result<f64, E>,
) -> Result<Option<f64>, E> {
    let Some(direction) = widest_horizontal(covariance, pose) else {
        return Ok(None);
    };
    let mut worst = f64::INFINITY;
    for side in [-1.0, 1.0] {
        let shifted = Pose::from_parts(
            (pose.translation.vector + direction * (side * SLIDE_PROBE_M)).into(),
            pose.rotation,
        );
        worst = worst.min(here - explained_at(&shifted)?);
    }
    Ok(Some(worst))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A corridor along x (walls at y = +-2 m, 3 m high, every 0.1 m): the share of a
    /// scan's points within 0.1 m of a wall point, by brute force.
    fn corridor() -> Vec<[f32; 3]> {
        let mut points = Vec::new();
        for i in 0..400 {
            for k in 0..30 {
                let (x, z) = (-20.0 + 0.1 * i as f32, 0.1 * k as f32);
                points.push([x, 2.0, z]);
                points.push([x, -2.0, z]);
            }
        }
        points
    }

    fn share_near(map: &[[f32; 3]], scan: &[[f32; 3]], pose: &Pose) -> f64 {
        let near = scan
            .iter()
            .filter(|p| {
                let q = pose * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                map.iter().any(|m| {
                    let d =
                        Vector3::new(f64::from(m[0]), f64::from(m[1]), f64::from(m[2])) - q.coords;
                    d.norm_squared() <= 0.01
                })
            })
            .count();
        near as f64 / scan.len() as f64
    }

    #[test]
    fn a_corridor_slides_along_its_axis_and_a_wall_across_it_pins() {
        let map = corridor();
        // The scan: a stretch of both walls, and a cross wall at x = 3 m (the corridor's
        // end as the scan saw it).
        let mut scan: Vec<[f32; 3]> = map
            .iter()
            .filter(|p| p[0].abs() < 5.0)
            .step_by(7)
            .copied()
            .collect();
        // The covariance's widest horizontal direction: along x (the corridor's axis).
        let mut covariance = Matrix6::identity() * 1e-4;
        covariance[(3, 3)] = 1.0;
        let pose = Pose::identity();
        assert_eq!(
            widest_horizontal(&covariance, &pose).map(|d| d.x.abs()),
            Some(1.0)
        );
        let explained = |at: &Pose| Ok::<_, ()>(share_near(&map, &scan, at));
        let here = explained(&pose).unwrap();
        let loss = slide_loss(&pose, &covariance, here, explained)
            .unwrap()
            .unwrap();
        assert!(loss.abs() < 1e-9, "the walls slide: {loss}");
        // The map gains a cross wall the scan sees: sliding now loses that wall's share.
        let mut map = map;
        let wall: Vec<[f32; 3]> = (0..40)
            .flat_map(|j| (0..30).map(move |k| [3.0, -2.0 + 0.1 * j as f32, 0.1 * k as f32]))
            .collect();
        map.extend(&wall);
        scan.extend(wall.iter().step_by(7));
        let explained = |at: &Pose| Ok::<_, ()>(share_near(&map, &scan, at));
        let here = explained(&pose).unwrap();
        let loss = slide_loss(&pose, &covariance, here, explained)
            .unwrap()
            .unwrap();
        let cross_share = wall.iter().step_by(7).count() as f64 / scan.len() as f64;
        assert!(
            (loss - cross_share).abs() < 0.02,
            "loss {loss}, the cross wall's share {cross_share}"
        );
        // A covariance that is not finite says nothing.
        let nan = Matrix6::from_element(f64::NAN);
        assert_eq!(slide_loss(&pose, &nan, here, explained), Ok(None));
    }

    #[test]
    fn structure_is_what_stands_above_the_floor() {
        // A floor at z = 0 (every 0.25 m) and a post 2 m high at (1.5, 1.5).
        let mut points: Vec<[f32; 3]> = (0..40)
            .flat_map(|i| (0..40).map(move |j| [0.25 * i as f32 - 5.0, 0.25 * j as f32 - 5.0, 0.0]))
            .collect();
        let post: Vec<[f32; 3]> = (0..200).map(|k| [1.5, 1.5, 0.01 * k as f32]).collect();
        points.extend(&post);
        let kept = structure(&points, &Pose::identity());
        assert!(kept.iter().all(|p| p[2] >= 1.0), "{kept:?}");
        assert_eq!(kept.len(), post.iter().filter(|p| p[2] >= 1.0).count());
    }
}
