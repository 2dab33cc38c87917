//! The up direction of a scan from its own geometry, for relocalizing without an IMU:
//! floors, ceilings and roads are the large planes whose normals lie near the sensor's
//! z axis (a hand-held or mounted sensor tilts, but not by more than `max_tilt`). The
//! estimate is the dominant direction of those normals, re-gated around itself.

use std::collections::HashMap;
use std::hash::BuildHasher;

use rustc_hash::FxBuildHasher;

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use kfmap_geometry::eigen::sorted_symmetric_eigen;
use kfmap_geometry::surfel::Surfel;

/// Voxel edges of the planes voted with, metres, finest first: a sparse scan (few
/// rings, or thinned before it was sent: `kfmap relocalize` sends 0.25 m voxels) has
/// too few floor points in a 1 m voxel, so the next scale is tried.
const PLANE_VOXELS_M: [f64; 3] = [1.0, 2.0, 4.0];
/// A voxel votes when it holds this many points...
const MIN_PLANE_POINTS: u32 = 8;
/// ... its smallest spread is below this share of the middle one (flat)...
const MAX_FLATNESS: f64 = 0.05;
/// ... and its middle spread (standard deviation) is at least this share of its edge:
/// one ring's arc through a voxel is flat in any plane holding it, so its normal
/// says nothing (a filled square's spread is 0.29 of its edge; two rings 0.2 apart, 0.1).
const MIN_WIDTH: f64 = 0.1;
/// A scale's estimate stands when this many voxels voted for it in the last gate.
const MIN_VOTING_VOXELS: usize = 5;

/// The up direction of a sensor-frame scan, or `None` when too few planes lie within
/// `max_tilt_deg` of the sensor's z axis to tell.
pub fn estimate_up(points: &[[f32; 3]], max_tilt_deg: f64) -> Option<Vector3<f64>> {
    PLANE_VOXELS_M
        .iter()
        .find_map(|&voxel| up_at_scale::<std::hash::RandomState>(points, max_tilt_deg, voxel))
}

/// [`estimate_up`] of a bake's own cloud (a keyframe's, for the place grid), the same
/// answer bit for bit: its voxels hashed with FxHash, about 4 % of a bake's time less
/// than SipHash (docs/DESIGN.md#notes-tiles). Scans from clients keep SipHash's keyed hashing.
pub fn estimate_map_up(points: &[[f32; 3]], max_tilt_deg: f64) -> Option<Vector3<f64>> {
    PLANE_VOXELS_M
        .iter()
        .find_map(|&voxel| up_at_scale::<FxBuildHasher>(points, max_tilt_deg, voxel))
}

/// [`estimate_up`] from the planes of `voxel`-metre voxels alone, hashed with `S`.
fn up_at_scale<S: BuildHasher + Default>(
    points: &[[f32; 3]],
    max_tilt_deg: f64,
    voxel: f64,
) -> Option<Vector3<f64>> {
    // Sized for a voxel per few points: growing it rehashed every voxel (2 % of a bake).
    let mut voxels: HashMap<[i32; 3], Surfel, S> =
        HashMap::with_capacity_and_hasher(points.len() / 8, S::default());
    for p in points {
        let v = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        if !v.iter().all(|c| c.is_finite()) {
            continue;
        }
        let key = [0, 1, 2].map(|a| (v[a] / voxel).floor() as i32);
        voxels.entry(key).or_default().add_point(v);
    }
    // In key order: summed in a hash map's (random) order, the estimate would differ in
    // its last bits from run to run, and so would the baked map's place grid.
    let mut voxels: Vec<([i32; 3], Surfel)> = voxels.into_iter().collect();
    voxels.sort_unstable_by_key(|(key, _)| *key);
    let min_width_sq = (MIN_WIDTH * voxel).powi(2);
    let normals: Vec<(Vector3<f64>, f64)> = voxels
        .iter()
        .map(|(_, s)| s)
        .filter(|s| s.num_points() >= MIN_PLANE_POINTS)
        .filter_map(|s| {
            let eigen = s.eigen();
            let values = eigen.values;
            (values[0] <= MAX_FLATNESS * values[1] && values[1] >= min_width_sq)
                .then(|| (eigen.vectors.column(0).into(), f64::from(s.num_points())))
        })
        .collect();
    let mut up = Vector3::z();
    // Gates narrow as the estimate settles: the first admits the tilt allowed.
    for gate_deg in [max_tilt_deg, max_tilt_deg / 2.0, max_tilt_deg / 4.0] {
        let cos_gate = gate_deg.to_radians().cos();
        let mut scatter = Matrix3::zeros();
        let mut votes = 0.0;
        let mut voting = 0;
        for (n, w) in &normals {
            if n.dot(&up).abs() >= cos_gate {
                scatter += *w * n * n.transpose();
                votes += w;
                voting += 1;
            }
        }
        if votes < f64::from(MIN_PLANE_POINTS) * 4.0 || voting < MIN_VOTING_VOXELS {
            return None;
        }
        let dominant: Vector3<f64> = sorted_symmetric_eigen(&scatter).vectors.column(2).into();
        up = if dominant.dot(&up) < 0.0 {
            -dominant
        } else {
            dominant
        };
    }
    Some(up.normalize())
}

/// The smallest rotation taking `up` (sensor frame) to +z: applied to the scan, it
/// levels it and keeps its heading as far as a tilt allows.
pub fn levelling(up: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(up, &Vector3::z()).unwrap_or_else(|| {
        // Upside down: half a turn about x.
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    })
}
