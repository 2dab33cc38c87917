//! The map's coarse occupancy grid with dilated levels, the index of the relocalization
//! search (after 3D-BBS, Aoki et al., ICRA 2024). Level 0 marks every voxel that holds a
//! map point; level `l` marks voxel `i` when any level-0 voxel in the cube
//! `i + [0, 2^l)^3` is marked. A search node covering the translations `t + k r`,
//! `k` in `[0, 2^l)^3`, then bounds the hits of all of them with one lookup per point.
//! Levels are dense bit arrays (x fastest), so a baked grid is read in place.

use std::collections::HashSet;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::level::{estimate_up, levelling};
use crate::options::{InvalidOption, ensure};

/// The translations searched: an axis-aligned box in the map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchRegion {
    /// Low corner, metres.
    pub min: [f64; 3],
    /// High corner, metres.
    pub max: [f64; 3],
}

/// Maps tilt less than this from their frame's z (baked from gravity-levelled or
/// reference poses); their floors are found within it.
const MAP_MAX_TILT_DEG: f64 = 20.0;

/// Most levels a grid holds (level 0 included): a top voxel spans `2^(LEVELS-1)`
/// level-0 voxels per axis.
pub const MAX_LEVELS: usize = 12;

/// Most voxels one level may hold: 2^31 bits (256 MiB per level).
pub const MAX_VOXELS: u64 = 1 << 31;

/// How the grid is cut.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridParams {
    /// Edge of a level-0 voxel, metres.
    pub resolution: f64,
    /// Levels, level 0 included.
    pub levels: usize,
    /// The grid keeps map points within this many metres (per axis) of the keyframes'
    /// positions: a scan's far returns say little about where it is.
    pub reach: f64,
    /// Relocalization searches translations within this many metres (x, y, z) of the
    /// box around the keyframes' positions.
    pub search_margin: [f64; 3],
}

impl Default for GridParams {
    /// One-metre voxels, levels up to 2^7 = 128 voxels.
    fn default() -> Self {
        Self {
            resolution: 1.0,
            levels: 8,
            reach: 40.0,
            search_margin: [12.0, 12.0, 1.0],
        }
    }
}

impl GridParams {
    /// Checks the values; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure(
            self.resolution.is_finite() && (0.05..=10.0).contains(&self.resolution),
            "place-resolution",
            self.resolution,
            "0.05 to 10 m",
        )?;
        ensure(
            (1..=MAX_LEVELS).contains(&self.levels),
            "place-levels",
            self.levels,
            "1 to 12",
        )?;
        ensure(
            self.reach.is_finite() && (1.0..=1000.0).contains(&self.reach),
            "place-reach",
            self.reach,
            "1 to 1000 m",
        )?;
        ensure(
            self.search_margin
                .iter()
                .all(|m| m.is_finite() && (0.0..=100.0).contains(m)),
            "place-search-margin",
            format!("{:?}", self.search_margin),
            "three margins of 0 to 100 m",
        )
    }
}

/// Why a grid could not be built or read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GridError {
    /// No finite point to mark.
    #[error("no finite map point to build the place grid from")]
    Empty,
    /// The map's extent at this resolution needs too many voxels.
    #[error(
        "the place grid would need {voxels} voxels of {resolution} m (at most {MAX_VOXELS}); \
         bake with a coarser place-resolution"
    )]
    TooLarge {
        /// Voxels needed.
        voxels: u64,
        /// Level-0 voxel edge, metres.
        resolution: f64,
    },
    /// A stored grid whose fields do not agree.
    #[error("place grid: {0}")]
    Corrupt(String),
}

/// Map points gathered for a grid: their voxels at half the grid's resolution (the
/// map's points are many; the grid needs where they are, not each one).
#[derive(Debug, Clone, Default)]
pub struct GridBuilder {
    fine: f64,
    keys: HashSet<[i64; 3]>,
    anchors: Vec<[f64; 3]>,
    /// Anchors whose surroundings relocalization searches (a tile's core keyframes; all
    /// anchors when empty).
    searched: Vec<[f64; 3]>,
    /// Sum of the up directions of the clouds added (map frame), each found from the
    /// cloud's own points as a scan's is.
    up_votes: Vector3<f64>,
}

impl GridBuilder {
    /// An empty builder for `params` (validated by the caller).
    pub fn new(params: &GridParams) -> Self {
        Self {
            fine: params.resolution / 2.0,
            keys: HashSet::new(),
            anchors: Vec::new(),
            searched: Vec::new(),
            up_votes: Vector3::zeros(),
        }
    }

    /// Adds one cloud's map-frame points (a keyframe's; non-finite ones are skipped).
    pub fn add_points(&mut self, points: impl IntoIterator<Item = [f64; 3]>) {
        let mut cloud: Vec<[f32; 3]> = Vec::new();
        for p in points {
            if p.iter().all(|v| v.is_finite()) {
                self.keys.insert(p.map(|v| (v / self.fine).floor() as i64));
                cloud.push(p.map(|v| v as f32));
            }
        }
        // Up as a scan from here finds it, so the grid levels alike (a map frame from
        // poses or gravity need not have its floors level).
        if let Some(up) = estimate_up(&cloud, MAP_MAX_TILT_DEG) {
            self.up_votes += up * cloud.len() as f64;
        }
    }

    /// Adds a sensor position the map was seen from (a keyframe's): the grid reaches
    /// `reach` metres around these, and relocalization searches near them.
    pub fn add_anchor(&mut self, position: [f64; 3]) {
        if position.iter().all(|v| v.is_finite()) {
            self.anchors.push(position);
        }
    }

    /// As [`Self::add_anchor`], for a sensor position whose surroundings relocalization
    /// searches while others' are only marked: a tile of a tile set searches its core,
    /// its halo's places being its neighbours' to find.
    pub fn add_searched_anchor(&mut self, position: [f64; 3]) {
        if position.iter().all(|v| v.is_finite()) {
            self.anchors.push(position);
            self.searched.push(position);
        }
    }

    /// The grid: levelled on the map's own floor-like planes (a map built from poses
    /// whose z is not quite gravity still levels alike with a levelled scan), clipped
    /// to `params.reach` around the anchors.
    pub fn finish(&self, params: &GridParams) -> Result<PlaceGrid, GridError> {
        if self.keys.is_empty() || self.anchors.is_empty() {
            return Err(GridError::Empty);
        }
        let centre = |k: &[i64; 3]| k.map(|v| (v as f64 + 0.5) * self.fine);
        let up = self.up_votes.try_normalize(1e-9).unwrap_or_else(Vector3::z);
        let grid_from_map = levelling(&up);
        let to_grid = |p: [f64; 3]| -> [f64; 3] { (grid_from_map * Vector3::from(p)).into() };
        let anchors: Vec<[f64; 3]> = self.anchors.iter().map(|a| to_grid(*a)).collect();
        let bounds = |points: &[[f64; 3]]| {
            let (mut low, mut high) = ([f64::MAX; 3], [f64::MIN; 3]);
            for a in points {
                for axis in 0..3 {
                    low[axis] = low[axis].min(a[axis]);
                    high[axis] = high[axis].max(a[axis]);
                }
            }
            (low, high)
        };
        let (low, high) = bounds(&anchors);
        let reach = params.reach;
        let r = params.resolution;
        let mut marked: HashSet<[i64; 3]> = HashSet::new();
        for k in &self.keys {
            let p = to_grid(centre(k));
            if (0..3).all(|a| p[a] >= low[a] - reach && p[a] <= high[a] + reach) {
                marked.insert(p.map(|v| (v / r).floor() as i64));
            }
        }
        let margin = params.search_margin;
        let (low, high) = if self.searched.is_empty() {
            (low, high)
        } else {
            bounds(
                &self
                    .searched
                    .iter()
                    .map(|a| to_grid(*a))
                    .collect::<Vec<_>>(),
            )
        };
        let region = SearchRegion {
            min: [low[0] - margin[0], low[1] - margin[1], low[2] - margin[2]],
            max: [
                high[0] + margin[0],
                high[1] + margin[1],
                high[2] + margin[2],
            ],
        };
        let q = grid_from_map.quaternion();
        PlaceGrid::from_voxels(&marked, params, [q.i, q.j, q.k, q.w], region)
    }
}

/// A built grid, owned.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaceGrid {
    /// Level-0 voxel edge, metres.
    pub resolution: f64,
    /// `R_grid_map` as qx qy qz qw: the grid's frame is the map's, levelled.
    pub grid_from_map: [f64; 4],
    /// World position of voxel (0, 0, 0)'s low corner, grid frame.
    pub origin: [f64; 3],
    /// Voxels per axis (every level has the same).
    pub dims: [u32; 3],
    /// Levels, level 0 first.
    pub levels: u32,
    /// Bits of every level, level after level, each `ceil(voxels / 64)` words.
    pub words: Vec<u64>,
    /// Translations relocalization searches, grid frame.
    pub region: SearchRegion,
}

impl PlaceGrid {
    /// The grid over marked level-0 voxel keys (`floor(p / resolution)` per axis, grid
    /// frame).
    pub fn from_voxels(
        marked: &HashSet<[i64; 3]>,
        params: &GridParams,
        grid_from_map: [f64; 4],
        region: SearchRegion,
    ) -> Result<Self, GridError> {
        let r = params.resolution;
        let mut low = [i64::MAX; 3];
        let mut high = [i64::MIN; 3];
        for key in marked {
            for a in 0..3 {
                low[a] = low[a].min(key[a]);
                high[a] = high[a].max(key[a]);
            }
        }
        if marked.is_empty() {
            return Err(GridError::Empty);
        }
        let span = |a: usize| (high[a] - low[a] + 1) as u64;
        let voxels = span(0).saturating_mul(span(1)).saturating_mul(span(2));
        if voxels > MAX_VOXELS {
            return Err(GridError::TooLarge {
                voxels,
                resolution: r,
            });
        }
        let dims = [span(0) as u32, span(1) as u32, span(2) as u32];
        let n = voxels as usize;
        let mut level = vec![false; n];
        let index =
            |x: usize, y: usize, z: usize| x + dims[0] as usize * (y + dims[1] as usize * z);
        for key in marked {
            let [x, y, z] = [0, 1, 2].map(|a| (key[a] - low[a]) as usize);
            level[index(x, y, z)] = true;
        }
        let words_per_level = n.div_ceil(64);
        let mut words = Vec::with_capacity(words_per_level * params.levels);
        pack(&level, &mut words);
        for l in 1..params.levels {
            dilate(&mut level, dims, 1 << (l - 1));
            pack(&level, &mut words);
        }
        Ok(Self {
            resolution: r,
            grid_from_map,
            origin: low.map(|v| v as f64 * r),
            dims,
            levels: params.levels as u32,
            words,
            region,
        })
    }

    /// The grid, read as a search reads it.
    pub fn view(&self) -> GridView<'_> {
        GridView::new(
            self.resolution,
            self.grid_from_map,
            self.origin,
            self.dims,
            self.levels,
            &self.words,
            self.region,
        )
        .expect("a built grid is consistent")
    }
}

/// Appends `bits` packed 64 per word.
fn pack(bits: &[bool], words: &mut Vec<u64>) {
    words.extend(bits.chunks(64).map(|chunk| {
        chunk
            .iter()
            .enumerate()
            .fold(0u64, |w, (i, &b)| w | (u64::from(b) << i))
    }));
}

/// One doubling of the dilation: each voxel also takes the marks `shift` voxels
/// further along each axis (separable, so three passes).
fn dilate(level: &mut [bool], dims: [u32; 3], shift: usize) {
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let strides = [1, nx, nx * ny];
    let extents = [nx, ny, nz];
    for axis in 0..3 {
        let (stride, extent) = (strides[axis], extents[axis]);
        if shift >= extent {
            // Nothing lies `shift` voxels further inside the grid.
            continue;
        }
        for i in 0..level.len() {
            let coordinate = (i / stride) % extent;
            if coordinate + shift < extent && level[i + shift * stride] {
                level[i] = true;
            }
        }
    }
}

/// A grid read in place (from a [`PlaceGrid`] or a baked map).
#[derive(Debug, Clone, Copy)]
pub struct GridView<'a> {
    resolution: f64,
    grid_from_map: UnitQuaternion<f64>,
    region: SearchRegion,
    origin: [f64; 3],
    dims: [i64; 3],
    levels: usize,
    words_per_level: usize,
    words: &'a [u64],
}

impl<'a> GridView<'a> {
    /// Checks that the fields agree (a baked grid's may have been written by anyone).
    pub fn new(
        resolution: f64,
        grid_from_map: [f64; 4],
        origin: [f64; 3],
        dims: [u32; 3],
        levels: u32,
        words: &'a [u64],
        region: SearchRegion,
    ) -> Result<Self, GridError> {
        let [qx, qy, qz, qw] = grid_from_map;
        let q = Quaternion::new(qw, qx, qy, qz);
        let region_ok = region
            .min
            .iter()
            .zip(&region.max)
            .all(|(a, b)| a.is_finite() && b.is_finite() && a <= b);
        if !(q.coords.iter().all(|v| v.is_finite()) && (q.norm() - 1.0).abs() < 1e-6 && region_ok) {
            return Err(GridError::Corrupt(format!(
                "rotation {grid_from_map:?} or search region {region:?} is invalid"
            )));
        }
        let voxels = dims.iter().map(|&d| u64::from(d)).product::<u64>();
        let words_per_level = voxels.div_ceil(64) as usize;
        let levels = levels as usize;
        if !(resolution.is_finite() && resolution > 0.0)
            || origin.iter().any(|v| !v.is_finite())
            || voxels == 0
            || voxels > MAX_VOXELS
            || !(1..=MAX_LEVELS).contains(&levels)
            || words.len() != words_per_level * levels
        {
            return Err(GridError::Corrupt(format!(
                "resolution {resolution}, dims {dims:?}, {levels} levels and {} words do not agree",
                words.len()
            )));
        }
        Ok(Self {
            resolution,
            grid_from_map: UnitQuaternion::new_unchecked(q),
            region,
            origin,
            dims: dims.map(i64::from),
            levels,
            words_per_level,
            words,
        })
    }

    /// Level-0 voxel edge, metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// `R_grid_map`: the grid's frame is the map's, levelled on its floors.
    pub fn grid_from_map(&self) -> UnitQuaternion<f64> {
        self.grid_from_map
    }

    /// Translations relocalization searches, grid frame.
    pub fn region(&self) -> SearchRegion {
        self.region
    }

    /// Grid-frame position of voxel (0, 0, 0)'s low corner.
    pub fn origin(&self) -> [f64; 3] {
        self.origin
    }

    /// Voxels per axis.
    pub fn dims(&self) -> [i64; 3] {
        self.dims
    }

    /// Levels, level 0 included.
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Bytes the levels take.
    pub fn bytes(&self) -> usize {
        self.words.len() * 8
    }

    /// True when voxel `v` is marked at `level`: some level-0 voxel of the cube
    /// `v + [0, 2^level)^3` is. A cube starting below the grid is answered by the
    /// grid's first voxel on that axis, whose cube covers the part inside (an upper
    /// bound, as a search needs).
    #[inline]
    pub fn marked(&self, level: usize, v: [i64; 3]) -> bool {
        let [nx, ny, nz] = self.dims;
        let side = 1_i64 << level;
        if v[0] >= nx || v[1] >= ny || v[2] >= nz || v.iter().any(|&c| c + side <= 0) {
            return false;
        }
        let [x, y, z] = v.map(|c| c.max(0));
        let i = (x + nx * (y + ny * z)) as usize;
        let word = self.words[level * self.words_per_level + i / 64];
        word >> (i % 64) & 1 == 1
    }

    /// The voxel holding world point `p` (may lie outside the grid).
    pub fn voxel_of(&self, p: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.origin[a]) / self.resolution).floor() as i64)
    }
}
