//! Voxel-grid downsampling: one centroid per occupied voxel, in a deterministic order.

use rayon::prelude::*;

use super::{CloudError, PointCloud};

/// Cells per axis that fit in a packed key (21 bits each, x in the high bits).
const MAX_CELLS: i64 = 1 << 21;

fn cell(c: f32, inv_size: f64) -> i64 {
    // `as i64` saturates, so far-away points cannot overflow.
    (c as f64 * inv_size).floor() as i64
}

/// Packs the cell of `p`, relative to the cell `origin`, into one sortable u64 whose
/// order equals the lexicographic order of (x, y, z) cells.
fn packed_key(p: &[f32; 3], inv_size: f64, origin: &[i64; 3]) -> u64 {
    let rel = |axis: usize| (cell(p[axis], inv_size) - origin[axis]) as u64;
    rel(0) << 42 | rel(1) << 21 | rel(2)
}

fn mean_of<const N: usize>(values: impl Iterator<Item = [f32; N]>) -> [f64; N] {
    let mut sum = [0.0f64; N];
    let mut n = 0usize;
    for v in values {
        for i in 0..N {
            sum[i] += v[i] as f64;
        }
        n += 1;
    }
    sum.map(|s| s / n.max(1) as f64)
}

impl PointCloud {
    /// Replaces the points of each occupied voxel (edge `voxel_size` metres, grid
    /// aligned with the origin) by their centroid. Attributes are averaged the same way;
    /// averaged view directions are re-normalized. Output is sorted by voxel key, so it
    /// does not depend on thread count. Non-finite points are skipped.
    pub fn voxel_downsample(&self, voxel_size: f64) -> Result<PointCloud, CloudError> {
        if !(voxel_size.is_finite() && voxel_size > 0.0) {
            return Err(CloudError::BadVoxelSize(voxel_size));
        }
        let inv_size = 1.0 / voxel_size;
        let Some(bbox) = self.bounding_box() else {
            return Ok(self.select(&[]));
        };
        let origin = bbox.min.map(|c| cell(c, inv_size));
        let cells =
            std::array::from_fn::<i64, 3, _>(|i| cell(bbox.max[i], inv_size) - origin[i] + 1);
        if cells.iter().any(|&n| n > MAX_CELLS) {
            return Err(CloudError::VoxelGridTooFine {
                voxel_size,
                cells: cells.into_iter().max().unwrap_or(0),
            });
        }
        let mut keyed: Vec<(u64, u32)> = self
            .points
            .par_iter()
            .enumerate()
            .filter(|(_, p)| p.iter().all(|c| c.is_finite()))
            .map(|(i, p)| (packed_key(p, inv_size, &origin), i as u32))
            .collect();
        keyed.par_sort_unstable();

        let mut out = PointCloud {
            points: Vec::new(),
            view_dirs: self.view_dirs.as_ref().map(|_| Vec::new()),
            intensity: self.intensity.as_ref().map(|_| Vec::new()),
            time: self.time.as_ref().map(|_| Vec::new()),
        };
        for group in keyed.chunk_by(|a, b| a.0 == b.0) {
            let members = || group.iter().map(|&(_, i)| i as usize);
            let centroid = mean_of(members().map(|i| self.points[i]));
            out.points.push(centroid.map(|c| c as f32));
            if let (Some(src), Some(dst)) = (&self.view_dirs, &mut out.view_dirs) {
                let m = mean_of(members().map(|i| src[i]));
                let norm = m.iter().map(|c| c * c).sum::<f64>().sqrt();
                // Opposing directions cancel: store "missing" (zero) rather than noise.
                let unit = if norm > 1e-6 {
                    m.map(|c| (c / norm) as f32)
                } else {
                    [0.0; 3]
                };
                dst.push(unit);
            }
            if let (Some(src), Some(dst)) = (&self.intensity, &mut out.intensity) {
                dst.push(mean_of(members().map(|i| [src[i]]))[0] as f32);
            }
            if let (Some(src), Some(dst)) = (&self.time, &mut out.time) {
                dst.push(mean_of(members().map(|i| [src[i]]))[0] as f32);
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    #[test]
    fn matches_brute_force_grouping() {
        // Oracle: group with a BTreeMap keyed by voxel, average in f64.
        let points: Vec<[f32; 3]> = (0..5000)
            .map(|i| {
                let t = i as f32 * 0.37;
                [
                    t.sin() * 7.3,
                    (t * 1.7).cos() * 4.1,
                    (t * 0.11).sin() * 2.0 - 0.3,
                ]
            })
            .collect();
        let cloud = PointCloud::from_points(points.clone());
        let size = 0.5;
        let mut groups: BTreeMap<[i64; 3], Vec<[f32; 3]>> = BTreeMap::new();
        for p in &points {
            let key = p.map(|c| (c as f64 / size).floor() as i64);
            groups.entry(key).or_default().push(*p);
        }
        let down = cloud.voxel_downsample(size).unwrap();
        assert_eq!(down.len(), groups.len());
        for (got, members) in down.points.iter().zip(groups.values()) {
            for axis in 0..3 {
                let want =
                    members.iter().map(|p| p[axis] as f64).sum::<f64>() / members.len() as f64;
                assert!((got[axis] as f64 - want).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn averages_attributes_and_renormalizes_view_dirs() {
        let mut cloud = PointCloud::from_points(vec![[0.1, 0.1, 0.1], [0.2, 0.2, 0.2]]);
        cloud.view_dirs = Some(vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
        cloud.intensity = Some(vec![2.0, 4.0]);
        let down = cloud.voxel_downsample(1.0).unwrap();
        assert_eq!(down.len(), 1);
        let v = down.view_dirs.unwrap()[0];
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert!((v[0] - h).abs() < 1e-6 && (v[1] - h).abs() < 1e-6 && v[2] == 0.0);
        assert_eq!(down.intensity.unwrap(), vec![3.0]);
    }

    #[test]
    fn too_fine_a_grid_is_an_error_not_a_wrong_answer() {
        let cloud = PointCloud::from_points(vec![[0.0; 3], [50_000.0, 0.0, 0.0]]);
        assert!(matches!(
            cloud.voxel_downsample(0.01),
            Err(CloudError::VoxelGridTooFine { .. })
        ));
        assert_eq!(cloud.voxel_downsample(1.0).unwrap().len(), 2);
    }

    #[test]
    fn rejects_bad_voxel_size() {
        let cloud = PointCloud::from_points(vec![[0.0; 3]]);
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(cloud.voxel_downsample(bad).is_err());
        }
    }
}
