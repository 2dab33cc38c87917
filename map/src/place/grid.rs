//! The map's coarse occupancy grid with dilated levels, the index of the relocalization
//! search (after 3D-BBS, Aoki et al., ICRA 2024). Level 0 marks every voxel that holds a
//! map point; level `l` marks voxel `i` when any level-0 voxel in the cube
//! `i + [0, 2^l)^3` is marked. A search node covering the translations `t + k r`,
//! `k` in `[0, 2^l)^3`, then bounds the hits of all of them with one lookup per point.
//! Levels are stored sparsely (blocks of 8^3 voxels holding a mark, found through a
//! hash table of plain arrays: see [`super::sparse`]), so a baked grid is read in
//! place and costs memory in proportion to what is mapped, not to its bounding box.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::level::{estimate_map_up, levelling};
use super::sparse::{
    self, ABSENT, BLOCK_EDGE, BLOCK_WORDS, EMPTY_KEY, MAX_EXTENT, ONES_BLOCK, SparseLevels,
    block_at, directory_index, home, key, shift_of, unentry, unkey,
};
use kfmap_geometry::options::{InvalidOption, ensure};
use rayon::prelude::*;

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

/// Most blocks of 8^3 voxels a grid may keep, all levels together: at most about
/// 1.4 GiB (64 bytes of bits and 24 of table per block), whatever the site's extent.
pub const MAX_BLOCKS: u64 = 1 << 24;

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
    /// What is mapped at this resolution needs too many blocks.
    #[error(
        "the place grid would need more than {blocks} blocks of 8^3 voxels of {resolution} m \
         (at most {MAX_BLOCKS}); bake with a coarser place-resolution"
    )]
    TooLarge {
        /// Blocks counted when the limit was passed.
        blocks: u64,
        /// Level-0 voxel edge, metres.
        resolution: f64,
    },
    /// The map spans too many voxels along one axis for the block keys.
    #[error(
        "the place grid would span {voxels} voxels of {resolution} m along one axis \
         (at most {MAX_EXTENT}); bake with a coarser place-resolution"
    )]
    TooWide {
        /// Voxels along the widest axis.
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
    /// The voxels of the clouds added, sorted and unique up to `sorted`; those of the
    /// clouds added since come after (sorted again once they outgrow that part: a
    /// sort of many keys is far cheaper than a hash insert per point).
    keys: Vec<[i64; 3]>,
    sorted: usize,
    anchors: Vec<[f64; 3]>,
    /// Sum of the up directions of the clouds added (map frame), each found from the
    /// cloud's own points as a scan's is.
    up_votes: Vector3<f64>,
}

/// One cloud's part of a grid ([`GridBuilder::contribution`]): found apart from the
/// builder, so clouds can be prepared in parallel and added in order.
#[derive(Debug, Clone, Default)]
pub struct GridContribution {
    /// Its voxels at the builder's resolution, sorted, unique.
    keys: Vec<[i64; 3]>,
    /// Its up direction weighted by its points (zero when it has no floor).
    up_vote: Vector3<f64>,
}

/// Keys held unsorted before a [`GridBuilder`] sorts them in (at least; few in unit
/// tests, so that their clouds are sorted in more than once).
const FIRST_SORT_KEYS: usize = if cfg!(test) { 1 << 10 } else { 1 << 20 };

impl GridBuilder {
    /// An empty builder for `params` (validated by the caller).
    pub fn new(params: &GridParams) -> Self {
        Self {
            fine: params.resolution / 2.0,
            ..Self::default()
        }
    }

    /// One cloud's map-frame points as a part of the grid (non-finite ones are skipped).
    pub fn contribution(&self, points: impl IntoIterator<Item = [f64; 3]>) -> GridContribution {
        let mut keys = Vec::new();
        let mut cloud: Vec<[f32; 3]> = Vec::new();
        for p in points {
            if p.iter().all(|v| v.is_finite()) {
                keys.push(p.map(|v| (v / self.fine).floor() as i64));
                cloud.push(p.map(|v| v as f32));
            }
        }
        keys.sort_unstable();
        keys.dedup();
        // Up as a scan from here finds it, so the grid levels alike (a map frame from
        // poses or gravity need not have its floors level).
        let up_vote = estimate_map_up(&cloud, MAP_MAX_TILT_DEG)
            .map_or_else(Vector3::zeros, |up| up * cloud.len() as f64);
        GridContribution { keys, up_vote }
    }

    /// Adds a cloud's part (clouds in the order the map holds them: the up votes sum
    /// in that order).
    pub fn add(&mut self, part: GridContribution) {
        self.keys.extend_from_slice(&part.keys);
        self.up_votes += part.up_vote;
        let unsorted = self.keys.len() - self.sorted;
        if unsorted > self.sorted.max(FIRST_SORT_KEYS) {
            self.keys.par_sort_unstable();
            self.keys.dedup();
            self.sorted = self.keys.len();
        }
    }

    /// Adds one cloud's map-frame points (a keyframe's; non-finite ones are skipped).
    pub fn add_points(&mut self, points: impl IntoIterator<Item = [f64; 3]>) {
        let part = self.contribution(points);
        self.add(part);
    }

    /// Adds a sensor position the map was seen from (a keyframe's): the grid reaches
    /// `reach` metres around these, and relocalization searches near them.
    pub fn add_anchor(&mut self, position: [f64; 3]) {
        if position.iter().all(|v| v.is_finite()) {
            self.anchors.push(position);
        }
    }

    /// The grid: levelled on the map's own floor-like planes (a map built from poses
    /// whose z is not quite gravity still levels alike with a levelled scan), clipped
    /// to `params.reach` around the anchors.
    pub fn finish(&self, params: &GridParams) -> Result<PlaceGrid, GridError> {
        self.marked_voxels(params)?.grid()
    }

    /// The grid's marked level-0 voxels, before its levels are built: what a tile set
    /// cuts every tile's grid from ([`MarkedVoxels::cut`]) without building the whole
    /// map's levels.
    pub fn marked_voxels(&self, params: &GridParams) -> Result<MarkedVoxels, GridError> {
        if self.keys.is_empty() || self.anchors.is_empty() {
            return Err(GridError::Empty);
        }
        let centre = |k: &[i64; 3]| k.map(|v| (v as f64 + 0.5) * self.fine);
        let grid_from_map =
            levelling(&self.up_votes.try_normalize(1e-9).unwrap_or_else(Vector3::z));
        let to_grid = |p: [f64; 3]| -> [f64; 3] { (grid_from_map * Vector3::from(p)).into() };
        let anchors: Vec<[f64; 3]> = self.anchors.iter().map(|a| to_grid(*a)).collect();
        let (low, high) = bounds(&anchors);
        let reach = params.reach;
        let r = params.resolution;
        // Keys may repeat (clouds added since the last sort): the voxels are made unique.
        let mut keys: Vec<[i64; 3]> = self
            .keys
            .par_iter()
            .filter_map(|k| {
                let p = to_grid(centre(k));
                (0..3)
                    .all(|a| p[a] >= low[a] - reach && p[a] <= high[a] + reach)
                    .then(|| p.map(|v| (v / r).floor() as i64))
            })
            .collect();
        keys.par_sort_unstable();
        keys.dedup();
        Ok(MarkedVoxels {
            keys,
            params: *params,
            grid_from_map,
            region: search_region(low, high, params, None),
        })
    }
}

/// A grid's marked level-0 voxels, its rotation and search region: a [`PlaceGrid`]
/// before its levels are built.
#[derive(Debug, Clone)]
pub struct MarkedVoxels {
    /// Voxel keys (grid frame, `floor(p / resolution)`), sorted (x, then y, then z), unique.
    keys: Vec<[i64; 3]>,
    params: GridParams,
    grid_from_map: UnitQuaternion<f64>,
    region: SearchRegion,
}

impl MarkedVoxels {
    /// The grid, its levels built.
    pub fn grid(&self) -> Result<PlaceGrid, GridError> {
        let q = self.grid_from_map.quaternion();
        PlaceGrid::from_voxels(&self.keys, &self.params, [q.i, q.j, q.k, q.w], self.region)
    }

    /// As [`PlaceGrid::cut_from`] on [`Self::grid`], without building the whole grid:
    /// each x row in the box found by galloping from the last, its y range by binary
    /// search (the keys are sorted).
    pub fn cut(
        &self,
        low: [f64; 2],
        high: [f64; 2],
        searched: &[[f64; 3]],
    ) -> Result<PlaceGrid, GridError> {
        let r = self.params.resolution;
        let first = low.map(|v| (v / r).floor() as i64);
        let last = high.map(|v| (v / r).floor() as i64);
        let mut marked = Vec::new();
        let mut at = self.keys.partition_point(|k| k[0] < first[0]);
        while at < self.keys.len() && self.keys[at][0] <= last[0] {
            let x = self.keys[at][0];
            let row = &self.keys[at..at + run_length(&self.keys[at..], |k| k[0] == x)];
            let from = row.partition_point(|k| k[1] < first[1]);
            let to = row.partition_point(|k| k[1] <= last[1]);
            marked.extend_from_slice(&row[from..to]);
            at += row.len();
        }
        tile_grid(
            &marked,
            self.params.levels,
            r,
            &self.grid_from_map,
            &self.region,
            searched,
        )
    }
}

/// How many of `items` from the first hold `pred` (true on a prefix), found by
/// galloping: a row of a large sorted array is found near where it starts, not by
/// binary searches over all of it (each a cache miss per step).
fn run_length<T>(items: &[T], pred: impl Fn(&T) -> bool) -> usize {
    let mut step = 1;
    while step < items.len() && pred(&items[step]) {
        step *= 2;
    }
    let (from, to) = (step / 2, step.min(items.len()));
    from + items[from..to].partition_point(&pred)
}

/// A tile's grid: `marked` (a whole grid's voxels in the tile's box), levelled as the
/// whole grid, its search region the whole's translations around `searched` (map frame).
fn tile_grid(
    marked: &[[i64; 3]],
    levels: usize,
    resolution: f64,
    grid_from_map: &UnitQuaternion<f64>,
    whole_region: &SearchRegion,
    searched: &[[f64; 3]],
) -> Result<PlaceGrid, GridError> {
    if searched.is_empty() {
        return Err(GridError::Empty);
    }
    let params = GridParams {
        resolution,
        levels,
        ..GridParams::default()
    };
    let searched: Vec<[f64; 3]> = searched
        .iter()
        .map(|p| (grid_from_map * Vector3::from(*p)).into())
        .collect();
    let (first_anchor, last_anchor) = bounds(&searched);
    let region = search_region(first_anchor, last_anchor, &params, Some(whole_region));
    let q = grid_from_map.quaternion();
    PlaceGrid::from_voxels(marked, &params, [q.i, q.j, q.k, q.w], region)
}

/// Box around `points`: (lowest, highest) per axis.
fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let (mut low, mut high) = ([f64::MAX; 3], [f64::MIN; 3]);
    for a in points {
        for axis in 0..3 {
            low[axis] = low[axis].min(a[axis]);
            high[axis] = high[axis].max(a[axis]);
        }
    }
    (low, high)
}

/// The translations searched around sensor positions spanning `[low, high]` (grid
/// frame): the box grown by the search margin. Within `whole` (the whole map's region,
/// for a tile), its corners are moved out onto that region's lattice (steps of the
/// resolution from its low corner) and kept inside it, so that a tile tries the whole
/// map's translations and no others.
fn search_region(
    low: [f64; 3],
    high: [f64; 3],
    params: &GridParams,
    whole: Option<&SearchRegion>,
) -> SearchRegion {
    let (margin, r) = (params.search_margin, params.resolution);
    let min = [0, 1, 2].map(|a| low[a] - margin[a]);
    let max = [0, 1, 2].map(|a| high[a] + margin[a]);
    match whole {
        None => SearchRegion { min, max },
        Some(whole) => {
            let o = whole.min;
            // The whole map's last translation per axis (its search's lattice ends there).
            let last = [0, 1, 2].map(|a| ((whole.max[a] - o[a]) / r).floor());
            SearchRegion {
                min: [0, 1, 2].map(|a| o[a] + ((min[a] - o[a]) / r).floor().max(0.0) * r),
                max: [0, 1, 2].map(|a| o[a] + ((max[a] - o[a]) / r).ceil().min(last[a]) * r),
            }
        }
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
    /// The levels' blocks: see [`SparseLevels`].
    pub levels_data: SparseLevels,
    /// Translations relocalization searches, grid frame.
    pub region: SearchRegion,
}

impl PlaceGrid {
    /// The grid over marked level-0 voxel keys (`floor(p / resolution)` per axis, grid
    /// frame; a key may repeat).
    pub fn from_voxels(
        marked: &[[i64; 3]],
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
        let widest = span(0).max(span(1)).max(span(2));
        if widest > MAX_EXTENT {
            return Err(GridError::TooWide {
                voxels: widest,
                resolution: r,
            });
        }
        let dims = [span(0) as u32, span(1) as u32, span(2) as u32];
        let relative: Vec<[i64; 3]> = marked
            .par_iter()
            .map(|k| [k[0] - low[0], k[1] - low[1], k[2] - low[2]])
            .collect();
        let levels_data = sparse::build(&relative, dims.map(i64::from), params.levels, MAX_BLOCKS)
            .map_err(|blocks| GridError::TooLarge {
                blocks,
                resolution: r,
            })?;
        Ok(Self {
            resolution: r,
            grid_from_map,
            origin: low.map(|v| v as f64 * r),
            dims,
            levels: params.levels as u32,
            levels_data,
            region,
        })
    }

    /// A tile's grid: `whole`'s marked voxels overlapping grid-frame `(x, y)` in `[low,
    /// high]` (a tile's core grown by the grid's reach), levelled as `whole`, searching
    /// around `searched` (map frame: the core's keyframe positions). A scan placed in
    /// the core then hits what it hits on the whole map, whichever keyframes the points
    /// came from, and the tile tries the whole map's translations there.
    pub fn cut_from(
        whole: &GridView<'_>,
        low: [f64; 2],
        high: [f64; 2],
        searched: &[[f64; 3]],
    ) -> Result<Self, GridError> {
        if searched.is_empty() {
            return Err(GridError::Empty);
        }
        let r = whole.resolution();
        let grid_from_map = whole.grid_from_map();
        let base = whole.origin().map(|o| (o / r).round() as i64);
        let dims = whole.dims();
        let first = [0, 1].map(|a| ((low[a] / r).floor() as i64 - base[a]).max(0));
        let last = [0, 1].map(|a| ((high[a] / r).floor() as i64 - base[a]).min(dims[a] - 1));
        let end = [last[0] + 1, last[1] + 1, dims[2]];
        // Cubes of an upper level first: one look skips a cube with nothing marked
        // (most of a site), level 0 is read only inside marked ones.
        let level = whole.levels().saturating_sub(1).min(3);
        let side = 1_i64 << level;
        // Each voxel is visited once: the keys are unique.
        let mut marked: Vec<[i64; 3]> = Vec::new();
        for cx in (first[0]..end[0]).step_by(side as usize) {
            for cy in (first[1]..end[1]).step_by(side as usize) {
                for cz in (0..end[2]).step_by(side as usize) {
                    if !whole.marked(level, [cx, cy, cz]) {
                        continue;
                    }
                    for x in cx..(cx + side).min(end[0]) {
                        for y in cy..(cy + side).min(end[1]) {
                            for z in cz..(cz + side).min(end[2]) {
                                if whole.marked(0, [x, y, z]) {
                                    marked.push([x + base[0], y + base[1], z + base[2]]);
                                }
                            }
                        }
                    }
                }
            }
        }
        tile_grid(
            &marked,
            whole.levels(),
            r,
            &grid_from_map,
            &whole.region(),
            searched,
        )
    }

    /// The grid, read as a search reads it.
    pub fn view(&self) -> GridView<'_> {
        GridView::new(
            self.resolution,
            self.grid_from_map,
            self.origin,
            self.dims,
            self.levels,
            &self.levels_data.directory,
            &self.levels_data.keys,
            &self.levels_data.entries,
            &self.levels_data.words,
            self.region,
        )
        .expect("a built grid is consistent")
    }
}

/// The mask of `count` voxels, all set, for [`GridView::count_marked_among`]: bit
/// `i % 64` of word `i / 64` stands for voxel `i`.
pub fn every_voxel(count: usize) -> Vec<u64> {
    let mut mask = vec![u64::MAX; count.div_ceil(64)];
    if let Some(last) = mask.last_mut()
        && !count.is_multiple_of(64)
    {
        *last = (1 << (count % 64)) - 1;
    }
    mask
}

/// How many of the items set in `among` pass `marked` (item `i`: bit `i % 64` of word
/// `i / 64`), their bits set in `hits`; stops as soon as fewer than `need` can pass and
/// then returns less than `need` ([`GridView::count_marked_among`]'s loop).
#[inline(always)]
fn count_set(
    among: &[u64],
    need: u32,
    hits: &mut [u64],
    mut marked: impl FnMut(usize) -> bool,
) -> u32 {
    let mut left: u32 = among.iter().map(|w| w.count_ones()).sum();
    let mut count = 0;
    for (w, &word) in among.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            if count + left < need {
                return count;
            }
            let bit = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            left -= 1;
            // Counted without a branch on the result: half the points hit, at random.
            let hit = marked(w * 64 + bit);
            count += u32::from(hit);
            hits[w] |= u64::from(hit) << bit;
        }
    }
    count
}

/// A grid read in place (from a [`PlaceGrid`] or a baked map).
#[derive(Debug, Clone, Copy)]
pub struct GridView<'a> {
    resolution: f64,
    grid_from_map: UnitQuaternion<f64>,
    region: SearchRegion,
    origin: [f64; 3],
    dims: [i64; 3],
    /// Blocks per axis.
    block_dims: [i64; 3],
    levels: usize,
    directory: &'a [u32],
    keys: &'a [u64],
    entries: &'a [u32],
    words: &'a [u64],
    /// Hash shift of the table (`64 - log2(keys.len())`).
    shift: u32,
}

/// One level's blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LevelBlocks {
    /// Blocks partly marked (bits stored).
    pub partial: usize,
    /// Blocks wholly marked (no bits).
    pub full: usize,
}

/// True when a block entry points past the levels or the bits.
fn bad_entry(value: u32, levels: usize, stored: u64) -> bool {
    let (base, first, full) = unentry(value);
    !(first < levels
        && first <= full
        && full <= levels
        && (full == first || base as usize > ONES_BLOCK)
        && u64::from(base) + (full - first) as u64 <= stored)
}

impl<'a> GridView<'a> {
    /// Checks that the fields agree (a baked grid's may have been written by anyone):
    /// every entry points at stored bits, every table key is a block of the grid found
    /// by probing from its home slot, and a free slot ends every probe.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        resolution: f64,
        grid_from_map: [f64; 4],
        origin: [f64; 3],
        dims: [u32; 3],
        levels: u32,
        directory: &'a [u32],
        keys: &'a [u64],
        entries: &'a [u32],
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
        let levels = levels as usize;
        let block_dims = dims.map(|d| (i64::from(d) + BLOCK_EDGE - 1) / BLOCK_EDGE);
        let spanned = block_dims.iter().map(|&d| d as u64).product::<u64>();
        let capacity = keys.len();
        let tables_ok = if directory.is_empty() {
            capacity >= 2 && capacity.is_power_of_two() && entries.len() == capacity
        } else {
            directory.len() as u64 == spanned && capacity == 0 && entries.is_empty()
        };
        let shape_ok = resolution.is_finite()
            && resolution > 0.0
            && origin.iter().all(|v| v.is_finite())
            && dims.iter().all(|&d| d > 0 && u64::from(d) <= MAX_EXTENT)
            && (1..=MAX_LEVELS).contains(&levels)
            && tables_ok
            && words.len().is_multiple_of(BLOCK_WORDS)
            && words.len() >= 2 * BLOCK_WORDS
            // The all-clear and all-set blocks that empty and full levels read.
            && words[..BLOCK_WORDS] == [0; BLOCK_WORDS]
            && words[BLOCK_WORDS..2 * BLOCK_WORDS] == [u64::MAX; BLOCK_WORDS];
        if !shape_ok {
            return Err(GridError::Corrupt(format!(
                "resolution {resolution}, dims {dims:?}, {levels} levels, a directory of {}, \
                 {} keys, {} entries and {} words do not agree",
                directory.len(),
                keys.len(),
                entries.len(),
                words.len()
            )));
        }
        let stored = (words.len() / BLOCK_WORDS) as u64;
        if let Some(i) = directory
            .iter()
            .position(|&v| v != ABSENT && bad_entry(v, levels, stored))
        {
            return Err(GridError::Corrupt(format!(
                "directory slot {i}: entry {:#x} points past the levels or bits",
                directory[i]
            )));
        }
        let shift = if capacity == 0 { 0 } else { shift_of(capacity) };
        let mut free = 0;
        for (i, (&k, &value)) in keys.iter().zip(entries).enumerate() {
            if k == EMPTY_KEY {
                free += 1;
                continue;
            }
            let b = unkey(k);
            let in_grid = key(b) == k && (0..3).all(|a| b[a] < block_dims[a]);
            if !in_grid || bad_entry(value, levels, stored) {
                return Err(GridError::Corrupt(format!(
                    "table slot {i}: block {b:?} (entry {value:#x}) lies outside the grid or \
                     points past the levels or bits"
                )));
            }
            let mut j = home(k, shift);
            while j != i {
                if keys[j] == EMPTY_KEY || keys[j] == k {
                    return Err(GridError::Corrupt(format!(
                        "table slot {i}: block {b:?} is not where a lookup finds it"
                    )));
                }
                j = (j + 1) & (capacity - 1);
            }
        }
        if capacity > 0 && free == 0 {
            return Err(GridError::Corrupt(
                "the block table has no free slot".into(),
            ));
        }
        Ok(Self {
            resolution,
            grid_from_map: UnitQuaternion::new_unchecked(q),
            region,
            origin,
            dims: dims.map(i64::from),
            block_dims,
            levels,
            directory,
            keys,
            entries,
            words,
            shift,
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

    /// Voxels per axis of level 0's bounding box.
    pub fn dims(&self) -> [i64; 3] {
        self.dims
    }

    /// Levels, level 0 included.
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Bytes the levels take (directory or table, and bits).
    pub fn bytes(&self) -> usize {
        self.directory.len() * 4
            + self.keys.len() * 8
            + self.entries.len() * 4
            + self.words.len() * 8
    }

    /// How blocks are found: "directory" (dense over the grid's blocks) or "hash
    /// table" (sparse sites), with its slots.
    pub fn index(&self) -> (&'static str, usize) {
        if self.directory.is_empty() {
            ("hash table", self.keys.len())
        } else {
            ("directory", self.directory.len())
        }
    }

    /// Blocks of each level, level 0 first.
    pub fn level_blocks(&self) -> Vec<LevelBlocks> {
        let mut out = vec![LevelBlocks::default(); self.levels];
        let table = self
            .keys
            .iter()
            .zip(self.entries)
            .filter(|(k, _)| **k != EMPTY_KEY)
            .map(|(_, v)| *v);
        let listed = self.directory.iter().copied().filter(|&v| v != ABSENT);
        for value in table.chain(listed) {
            let (_, first, full) = unentry(value);
            for (l, level) in out.iter_mut().enumerate().skip(first) {
                if l < full {
                    level.partial += 1;
                } else {
                    level.full += 1;
                }
            }
        }
        out
    }

    /// True when voxel `v` is marked at `level`: some level-0 voxel of the cube
    /// `v + [0, 2^level)^3` is. A cube starting below the grid is answered by the
    /// grid's first voxel on that axis, whose cube covers the part inside (an upper
    /// bound, as a search needs: the bound the search's answers were measured with).
    #[inline]
    pub fn marked(&self, level: usize, v: [i64; 3]) -> bool {
        let Some(v) = self.clamped(level, v) else {
            return false;
        };
        let b = v.map(|c| c >> 3);
        let value = if self.directory.is_empty() {
            self.entry_of(key(b))
        } else {
            self.directory[directory_index(b, self.block_dims)]
        };
        self.bit(value, level, v)
    }

    /// How many of `voxels`, each moved by `shift`, are marked at `level` (as
    /// [`Self::marked`]).
    pub fn count_marked(&self, level: usize, voxels: &[[i64; 3]], shift: [i64; 3]) -> u32 {
        let among = every_voxel(voxels.len());
        let mut hits = vec![0; among.len()];
        self.count_marked_among(level, voxels, shift, &among, 0, &mut hits)
    }

    /// As [`Self::count_marked`] over the voxels whose bit is set in `among` (bit `i % 64`
    /// of word `i / 64`: voxel `i`), setting the bits of those marked in `hits` (cleared
    /// first): a search's bound, its hot loop. A child node of the search needs only its
    /// parent's hits, since a marked level-`l` cube holds the marked level-`(l-1)` ones.
    /// Stops as soon as fewer than `need` can be marked, and then returns less than
    /// `need` (`hits` partial); otherwise the exact count.
    pub fn count_marked_among(
        &self,
        level: usize,
        voxels: &[[i64; 3]],
        shift: [i64; 3],
        among: &[u64],
        need: u32,
        hits: &mut [u64],
    ) -> u32 {
        hits.fill(0);
        if self.directory.is_empty() {
            // Neighbouring voxels (a scan's, in scan order) often share a block, whose
            // entry is then looked up once.
            let mut last = (EMPTY_KEY, ABSENT);
            count_set(among, need, hits, |i| {
                self.moved_marked(level, voxels.get(i), shift, |b| {
                    let k = key(b);
                    if k != last.0 {
                        last = (k, self.entry_of(k));
                    }
                    last.1
                })
            })
        } else {
            count_set(among, need, hits, |i| {
                self.moved_marked(level, voxels.get(i), shift, |b| {
                    self.directory[directory_index(b, self.block_dims)]
                })
            })
        }
    }

    /// Whether `voxel` moved by `shift` is marked at `level` (false for none), with
    /// `entry` finding a block's entry.
    #[inline(always)]
    fn moved_marked(
        &self,
        level: usize,
        voxel: Option<&[i64; 3]>,
        shift: [i64; 3],
        entry: impl FnOnce([i64; 3]) -> u32,
    ) -> bool {
        voxel
            .and_then(|u| self.clamped(level, [u[0] + shift[0], u[1] + shift[1], u[2] + shift[2]]))
            .is_some_and(|v| self.bit(entry(v.map(|c| c >> 3)), level, v))
    }

    /// `v` clamped to the grid's first voxel per axis, or `None` when the cube
    /// `v + [0, 2^level)^3` misses the grid.
    #[inline]
    fn clamped(&self, level: usize, v: [i64; 3]) -> Option<[i64; 3]> {
        let [nx, ny, nz] = self.dims;
        let side = 1_i64 << level;
        if v[0] >= nx || v[1] >= ny || v[2] >= nz || v.iter().any(|&c| c + side <= 0) {
            return None;
        }
        Some(v.map(|c| c.max(0)))
    }

    /// The table entry of block key `k`, [`ABSENT`] when the block is empty at every
    /// level.
    #[inline]
    fn entry_of(&self, k: u64) -> u32 {
        let mask = self.keys.len() - 1;
        let mut i = home(k, self.shift);
        loop {
            let found = self.keys[i];
            if found == k {
                return self.entries[i];
            }
            if found == EMPTY_KEY {
                return ABSENT;
            }
            i = (i + 1) & mask;
        }
    }

    /// Voxel `v`'s bit at `level` in the block whose entry is `value`.
    #[inline]
    fn bit(&self, value: u32, level: usize, v: [i64; 3]) -> bool {
        let [x, y, z] = v.map(|c| c & (BLOCK_EDGE - 1));
        let word = self.words[block_at(value, level) * BLOCK_WORDS + z as usize];
        word >> (x + 8 * y) & 1 == 1
    }

    /// The voxel holding world point `p` (may lie outside the grid).
    pub fn voxel_of(&self, p: [f64; 3]) -> [i64; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.origin[a]) / self.resolution).floor() as i64)
    }
}
