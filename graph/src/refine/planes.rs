//! Planes for the refinement: the scans' points at their current poses cut by adaptive
//! voxels (a root cube that is not planar is split into eight, a few times), each plane
//! kept as one point cluster per scan that sees it, in that scan's own frame.

use std::ops::Range;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::RefineParams;
use kfmap_geometry::eigen::sorted_symmetric_eigen;
use kfmap_geometry::geometry::Pose;

/// Count, mean and centred scatter of a set of points (BALM's point cluster, centred so
/// nothing cancels far from the origin).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Cluster {
    /// Weight (the point count, or less when capped).
    pub n: f64,
    /// Mean point.
    pub mean: Vector3<f64>,
    /// `sum (p - mean)(p - mean)^T`, times the weight's share.
    pub scatter: Matrix3<f64>,
}

impl Cluster {
    /// The cluster of `points` (at least one).
    pub fn of(points: &[Vector3<f64>]) -> Self {
        let n = points.len() as f64;
        let mean = points.iter().sum::<Vector3<f64>>() / n;
        let scatter = points
            .iter()
            .map(|p| (p - mean) * (p - mean).transpose())
            .sum();
        Self { n, mean, scatter }
    }

    /// The same points moved by `pose`.
    pub fn moved(&self, pose: &Pose) -> Self {
        let r = pose.rotation.to_rotation_matrix();
        Self {
            n: self.n,
            mean: pose.transform_point(&self.mean.into()).coords,
            scatter: r.matrix() * self.scatter * r.matrix().transpose(),
        }
    }

    /// The union of clusters (the parallel-axis rule).
    pub fn merged<'a>(clusters: impl Iterator<Item = &'a Cluster> + Clone) -> Self {
        let n: f64 = clusters.clone().map(|c| c.n).sum();
        let mean = clusters.clone().map(|c| c.mean * c.n).sum::<Vector3<f64>>() / n;
        let scatter = clusters
            .map(|c| c.scatter + (c.mean - mean) * (c.mean - mean).transpose() * c.n)
            .sum();
        Self { n, mean, scatter }
    }

    /// The cluster weighted down to at most `cap` points (mean unchanged).
    pub fn capped(self, cap: f64) -> Self {
        let share = (cap / self.n).min(1.0);
        Self {
            n: self.n * share,
            mean: self.mean,
            scatter: self.scatter * share,
        }
    }
}

/// One plane: the scans that see it and their points there (each in its scan's frame),
/// sorted by scan.
#[derive(Debug, Clone)]
pub(crate) struct Plane {
    pub observers: Vec<(usize, Cluster)>,
}

/// A point being cut into voxels: its scan, where it is in the map and in its scan.
#[derive(Clone, Copy)]
struct Item {
    scan: u32,
    world: Vector3<f64>,
    local: Vector3<f64>,
}

/// The planes of `clouds` at `poses` (deterministic: in root-voxel order).
pub(crate) fn find_planes(
    clouds: &[&[[f32; 3]]],
    poses: &[Pose],
    params: &RefineParams,
) -> Vec<Plane> {
    let size = params.voxel_size;
    let all: Vec<usize> = (0..clouds.len()).collect();
    let keyed = keyed_points(clouds, poses, &all, size);
    let mut planes: Vec<Plane> = runs(&keyed, |e| e.0)
        .into_par_iter()
        .map(|range| {
            let key = keyed[range.start].0;
            let items: Vec<Item> = keyed[range]
                .iter()
                .map(|&(_, scan, k)| {
                    let p = clouds[scan as usize][k as usize];
                    let local = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                    Item {
                        scan,
                        world: poses[scan as usize].transform_point(&local.into()).coords,
                        local,
                    }
                })
                .collect();
            let centre = voxel_centre(key, size);
            let mut planes = Vec::new();
            cut(items, centre, size / 2.0, 0, poses, params, &mut planes);
            planes
        })
        .collect::<Vec<_>>()
        .into_iter()
        .flatten()
        .collect();
    // Planes seen from nearby scans next to each other: their pair blocks land in the same
    // part of the sparse matrix, which stays in cache (stable: deterministic).
    planes.sort_by_key(|p: &Plane| p.observers[0].0);
    planes
}

/// Keeps the voxel's points as a plane when they form one, else splits the voxel.
fn cut(
    items: Vec<Item>,
    centre: Vector3<f64>,
    half: f64,
    depth: u32,
    poses: &[Pose],
    params: &RefineParams,
    planes: &mut Vec<Plane>,
) {
    if items.len() < params.min_points {
        return;
    }
    let world: Vec<Vector3<f64>> = items.iter().map(|i| i.world).collect();
    let all = Cluster::of(&world);
    let eigen = sorted_symmetric_eigen(&all.scatter);
    let planar = eigen.values[0] <= params.plane_ratio * eigen.values[1]
        && (eigen.values[0].max(0.0) / all.n).sqrt() <= params.max_thickness;
    if planar {
        if let Some(plane) = plane_of(&items, poses, params) {
            planes.push(plane);
        }
        return;
    }
    if depth >= params.max_depth {
        return;
    }
    let mut octants: [Vec<Item>; 8] = Default::default();
    for item in items {
        let d = item.world - centre;
        let o = (d.x >= 0.0) as usize | ((d.y >= 0.0) as usize) << 1 | ((d.z >= 0.0) as usize) << 2;
        octants[o].push(item);
    }
    for (o, part) in octants.into_iter().enumerate() {
        let sign = |bit: usize| if o & bit != 0 { 1.0 } else { -1.0 };
        let offset = Vector3::new(sign(1), sign(2), sign(4)) * (half / 2.0);
        cut(
            part,
            centre + offset,
            half / 2.0,
            depth + 1,
            poses,
            params,
            planes,
        );
    }
}

/// The plane of a planar voxel's points: one cluster per scan (its own frame), without
/// the scans whose points sit away from the common plane, at most `max-observers` of
/// them spread evenly over the run. `None` when too few scans remain.
fn plane_of(items: &[Item], poses: &[Pose], params: &RefineParams) -> Option<Plane> {
    // Items arrive sorted by scan (the root sort keeps its order through the splits).
    let observers: Vec<(usize, Cluster)> = runs(items, |i| i.scan)
        .into_iter()
        .map(|run| {
            let local: Vec<Vector3<f64>> = items[run.clone()].iter().map(|i| i.local).collect();
            (items[run.start].scan as usize, Cluster::of(&local))
        })
        .collect();
    if observers.len() < params.min_observers {
        return None;
    }
    // The common plane, and each scan's offset from it.
    let moved: Vec<Cluster> = observers.iter().map(|(s, c)| c.moved(&poses[*s])).collect();
    let all = Cluster::merged(moved.iter());
    let normal = sorted_symmetric_eigen(&all.scatter)
        .vectors
        .column(0)
        .into_owned();
    let kept: Vec<(usize, Cluster)> = observers
        .into_iter()
        .zip(&moved)
        .filter(|(_, m)| normal.dot(&(m.mean - all.mean)).abs() <= params.max_offset)
        .map(|((s, c), _)| (s, c.capped(params.max_observer_points as f64)))
        .collect();
    if kept.len() < params.min_observers {
        return None;
    }
    let cap = params.max_observers;
    let observers = if kept.len() > cap {
        // Evenly spread over the scans that see it, so a revisit keeps its share.
        (0..cap)
            .map(|k| kept[(k * (kept.len() - 1) + (cap - 1) / 2) / (cap - 1)])
            .collect()
    } else {
        kept
    };
    Some(Plane { observers })
}

/// Voxel indices are packed in 21 bits per axis around the origin (+-2^20 voxels: +-2000
/// km at 2 m), so a point is sorted as 16 bytes instead of 32.
const AXIS_BITS: u32 = 21;
const AXIS_OFFSET: i64 = 1 << (AXIS_BITS - 1);

/// The points of `scans` (indices into `clouds`) at `poses`, as (voxel key for edge
/// `size`, scan, point index), sorted by voxel, then scan, then point.
pub(crate) fn keyed_points(
    clouds: &[&[[f32; 3]]],
    poses: &[Pose],
    scans: &[usize],
    size: f64,
) -> Vec<(u64, u32, u32)> {
    let mut keyed: Vec<(u64, u32, u32)> = scans
        .par_iter()
        .flat_map_iter(|&scan| {
            let pose = poses[scan];
            clouds[scan].iter().enumerate().map(move |(k, p)| {
                let w = pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let key = (0..3).fold(0u64, |key, a| {
                    let index =
                        ((w[a] / size).floor() as i64 + AXIS_OFFSET).clamp(0, (1 << AXIS_BITS) - 1);
                    (key << AXIS_BITS) | index as u64
                });
                (key, scan as u32, k as u32)
            })
        })
        .collect();
    keyed.par_sort_unstable();
    keyed
}

/// The centre of the voxel `key` names (edge `size`).
fn voxel_centre(key: u64, size: f64) -> Vector3<f64> {
    let mask = (1u64 << AXIS_BITS) - 1;
    Vector3::from_fn(|a, _| {
        let index = ((key >> (AXIS_BITS * (2 - a as u32))) & mask) as i64 - AXIS_OFFSET;
        (index as f64 + 0.5) * size
    })
}

/// The ranges of consecutive items with equal keys (`items` sorted by that key).
pub(crate) fn runs<T, K: PartialEq>(items: &[T], key: impl Fn(&T) -> K) -> Vec<Range<usize>> {
    let mut ranges = Vec::new();
    let mut start = 0;
    for k in 1..=items.len() {
        if k == items.len() || key(&items[k]) != key(&items[start]) {
            ranges.push(start..k);
            start = k;
        }
    }
    ranges
}

/// Scans that see fewer than `min-planes-per-scan` planes.
pub(crate) fn weak_scans(planes: &[Plane], scans: usize, params: &RefineParams) -> Vec<usize> {
    let mut count = vec![0usize; scans];
    for plane in planes {
        for (s, _) in &plane.observers {
            count[*s] += 1;
        }
    }
    (0..scans)
        .filter(|&s| count[s] < params.min_planes_per_scan)
        .collect()
}
