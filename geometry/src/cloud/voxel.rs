//! Voxel-grid downsampling: one centroid per occupied voxel, in a deterministic order.

use rayon::prelude::*;

use super::{CloudError, PointCloud};
use crate::geometry::{Pose, transform_point};

/// At most this many cells per axis, so the dense number of a cell in the widest grid
/// (2^63 cells) fits in a u64.
const MAX_CELLS: i64 = 1 << 21;

/// Points per parallel task: smaller pieces cost more in scheduling than they save.
const CHUNK: usize = 4096;

/// `floor(c * inv_size)`, saturated to the i64 range.
fn cell(c: f64, inv_size: f64) -> i64 {
    // floor() without a libm call (baseline x86-64 has no rounding instruction); `as
    // i64` saturates, so far-away points cannot overflow.
    let x = c * inv_size;
    let truncated = x as i64;
    truncated.saturating_sub(i64::from((truncated as f64) > x))
}

/// Where point `p` falls on the grid of the frame `grid_from_points` maps it into
/// (`None` = its own frame), or `None` for a non-finite point.
pub fn grid_position(p: &[f32; 3], grid_from_points: Option<&Pose>) -> Option<[f64; 3]> {
    let finite = p.iter().all(|c| c.is_finite());
    finite.then(|| match grid_from_points {
        None => p.map(f64::from),
        Some(pose) => transform_point(pose, p).into(),
    })
}

/// Point indices `0..n` grouped by voxel (edge `voxel_size` metres, grid aligned with
/// the origin), each at `position(i)` (`None` skips it): `(voxel key, index)` sorted by
/// key, then index; keys follow the lexicographic order of (x, y, z) cells and mean
/// nothing outside one call. Slice it with `chunk_by` on the key.
pub fn voxel_groups(
    n: usize,
    voxel_size: f64,
    position: impl Fn(usize) -> Option<[f64; 3]> + Sync,
) -> Result<Vec<(u64, u32)>, CloudError> {
    if !(voxel_size.is_finite() && voxel_size > 0.0) {
        return Err(CloudError::BadVoxelSize(voxel_size));
    }
    let inv_size = 1.0 / voxel_size;
    let cell_of = |i: usize| Some(position(i)?.map(|c| cell(c, inv_size)));
    // The occupied cells' range: cells are numbered densely inside it.
    let bounds = (0..n)
        .into_par_iter()
        .with_min_len(CHUNK)
        .filter_map(cell_of)
        .map(|c| (c, c))
        .reduce_with(|(low, high), (a, b)| {
            (
                std::array::from_fn(|k| low[k].min(a[k])),
                std::array::from_fn(|k| high[k].max(b[k])),
            )
        });
    let Some((low, high)) = bounds else {
        return Ok(Vec::new());
    };
    let extent: [i64; 3] =
        std::array::from_fn(|axis| high[axis].saturating_sub(low[axis]).saturating_add(1));
    if let Some(&widest) = extent.iter().filter(|&&n| n > MAX_CELLS).max() {
        return Err(CloudError::VoxelGridTooFine {
            voxel_size,
            cells: widest,
        });
    }
    // x slowest, z fastest: the order of (x, y, z), in as few bits as the grid needs,
    // so the radix sort below makes few passes.
    let number = |c: [i64; 3]| {
        let rel = |axis: usize| (c[axis] - low[axis]) as u64;
        (rel(0) * extent[1] as u64 + rel(1)) * extent[2] as u64 + rel(2)
    };
    let mut keyed: Vec<(u64, u32)> = (0..n)
        .into_par_iter()
        .with_min_len(CHUNK)
        .filter_map(|i| Some((number(cell_of(i)?), i as u32)))
        .collect();
    // Stable, so a voxel's indices stay ascending.
    radsort::sort_by_key(&mut keyed, |k| k.0);
    Ok(keyed)
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

/// A mean of directions, re-normalized; opposing directions cancel to "missing" (zero)
/// rather than noise.
pub fn unit_or_zero(m: [f64; 3]) -> [f32; 3] {
    let norm = m.iter().map(|c| c * c).sum::<f64>().sqrt();
    if norm > 1e-6 {
        m.map(|c| (c / norm) as f32)
    } else {
        [0.0; 3]
    }
}

/// A downsampled cloud and how many input points each of its points stands for.
#[derive(Debug, Clone)]
pub struct Voxelized {
    /// One centroid per occupied voxel, sorted by voxel key.
    pub cloud: PointCloud,
    /// Input points averaged into each centroid (>= 1).
    pub counts: Vec<u32>,
}

impl PointCloud {
    /// Replaces the points of each occupied voxel (edge `voxel_size` metres, grid
    /// aligned with the origin) by their centroid. Attributes are averaged the same way;
    /// averaged view directions are re-normalized. Output is sorted by voxel key, so it
    /// does not depend on thread count. Non-finite points are skipped.
    pub fn voxel_downsample(&self, voxel_size: f64) -> Result<PointCloud, CloudError> {
        Ok(self.voxelize(voxel_size, None)?.cloud)
    }

    /// As [`PointCloud::voxel_downsample`], on the grid of another frame when
    /// `grid_from_cloud` is given (e.g. a keyframe voxelized on the map's grid, so that
    /// keyframes seeing the same place share voxels); centroids stay in the cloud's own
    /// frame. Also returns each centroid's point count.
    pub fn voxelize(
        &self,
        voxel_size: f64,
        grid_from_cloud: Option<&Pose>,
    ) -> Result<Voxelized, CloudError> {
        let keyed = voxel_groups(self.len(), voxel_size, |i| {
            grid_position(&self.points[i], grid_from_cloud)
        })?;
        let groups: Vec<&[(u64, u32)]> = keyed.chunk_by(|a, b| a.0 == b.0).collect();
        let average = |values: &[[f32; 3]]| -> Vec<[f64; 3]> {
            groups
                .par_iter()
                .with_min_len(CHUNK / 4)
                .map(|group| mean_of(group.iter().map(|&(_, i)| values[i as usize])))
                .collect()
        };
        let average_scalar = |values: &[f32]| -> Vec<f32> {
            groups
                .par_iter()
                .with_min_len(CHUNK / 4)
                .map(|group| mean_of(group.iter().map(|&(_, i)| [values[i as usize]]))[0] as f32)
                .collect()
        };
        let out = PointCloud {
            points: average(&self.points)
                .into_iter()
                .map(|c| c.map(|c| c as f32))
                .collect(),
            view_dirs: self
                .view_dirs
                .as_ref()
                .map(|v| average(v).into_iter().map(unit_or_zero).collect()),
            intensity: self.intensity.as_deref().map(average_scalar),
            time: self.time.as_deref().map(average_scalar),
        };
        let counts = groups.iter().map(|g| g.len() as u32).collect();
        Ok(Voxelized { cloud: out, counts })
    }

    /// The scan as a keyframe keeps it: voxelized at `voxel_size` (0 = as it is); with
    /// `map_from_cloud`, on the map frame's grid and with each point's raw count, the
    /// weights the fusion of overlapping keyframes needs.
    pub fn into_keyframe_points(
        self,
        voxel_size: f64,
        map_from_cloud: Option<&Pose>,
    ) -> Result<(PointCloud, Option<Vec<u32>>), CloudError> {
        if voxel_size == 0.0 {
            return Ok((self, None));
        }
        let v = self.voxelize(voxel_size, map_from_cloud)?;
        Ok((v.cloud, map_from_cloud.map(|_| v.counts)))
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
    fn voxelizes_on_another_frames_grid_with_counts() {
        // Oracle: group by the voxel of each point moved into the grid frame; the
        // centroid stays in the cloud's own frame.
        let points: Vec<[f32; 3]> = (0..3000)
            .map(|i| {
                let t = i as f32 * 0.53;
                [t.cos() * 6.0, (t * 1.3).sin() * 3.0, (t * 0.07).cos()]
            })
            .collect();
        let grid_from_cloud = Pose::new(
            nalgebra::Vector3::new(0.31, -0.17, 0.05),
            nalgebra::Vector3::new(0.02, -0.01, 0.6),
        );
        let size = 0.4;
        let mut groups: BTreeMap<[i64; 3], Vec<[f32; 3]>> = BTreeMap::new();
        for p in &points {
            let q: [f64; 3] = transform_point(&grid_from_cloud, p).into();
            groups
                .entry(q.map(|c| (c / size).floor() as i64))
                .or_default()
                .push(*p);
        }
        let v = PointCloud::from_points(points)
            .voxelize(size, Some(&grid_from_cloud))
            .unwrap();
        assert_eq!(v.cloud.len(), groups.len());
        for ((got, count), members) in v.cloud.points.iter().zip(&v.counts).zip(groups.values()) {
            assert_eq!(*count as usize, members.len());
            for axis in 0..3 {
                let want =
                    members.iter().map(|p| p[axis] as f64).sum::<f64>() / members.len() as f64;
                assert!((got[axis] as f64 - want).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn cells_are_floors() {
        let values = [
            0.0, -0.0, 0.5, -0.5, 1.0, -1.0, 2.999_999, -2.000_001, 1e17, -1e17, 1e30, -1e30,
        ];
        for x in values {
            assert_eq!(cell(x, 1.0), x.floor() as i64, "{x}");
            assert_eq!(cell(x, 4.0), (x * 4.0).floor() as i64, "{x} / 0.25");
        }
    }

    #[test]
    fn the_same_output_on_any_thread_count() {
        let points: Vec<[f32; 3]> = (0..20_000)
            .map(|i| {
                let t = i as f32 * 0.013;
                [t.sin() * 9.0, (t * 2.3).cos() * 5.0, (t * 0.7).sin()]
            })
            .collect();
        let mut cloud = PointCloud::from_points(points);
        cloud.intensity = Some((0..20_000).map(|i| (i % 97) as f32).collect());
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| cloud.voxelize(0.3, None).unwrap())
        };
        let (one, two) = (on(1), on(2));
        assert_eq!(one.cloud.points, two.cloud.points);
        assert_eq!(one.cloud.intensity, two.cloud.intensity);
        assert_eq!(one.counts, two.counts);
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
