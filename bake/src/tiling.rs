//! Baking a map as a tile set (`kfmap bake --tile-size`, docs/DESIGN.md#notes-tiles): one
//! `.kfmap` per tile with the keyframes of its core square and of its halo, the index
//! `tiles.toml`, and for Autoware each core square's points as `<id>.pcd` with
//! `pointcloud_map_metadata.yaml`. Each keyframe is built once and its bytes go to every
//! tile holding it, so a tile answers exactly as the whole map does for a request it owns.

use std::collections::btree_map::Entry;
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{
    IoError, PcdData, sync_file_system, write_atomic, write_pcd, write_replacing,
};
use kfmap_map::archive::{
    ArchiveError, GravityRecord, MapWriter, OpenOptions, SerializedKeyframe, WriteSummary, open_map,
};
use kfmap_map::covis::CovisSnapshot;
use kfmap_map::map::{Keyframe, KeyframeMapOptions};
use kfmap_map::place::{GridBuilder, GridContribution, GridError, GridParams, MarkedVoxels};
use kfmap_map::select::{SURROUNDINGS, SelectionOptions, rank, select_active};
use kfmap_map::tiles::{
    AUTOWARE_METADATA_FILE, INDEX_FILE, INDEX_FORMAT, TileEntry, TileGeometry, TileIndex, tile_id,
};
use rayon::prelude::*;

use crate::error::BakeError;

/// The voxel (metres) the Autoware point clouds are thinned to: keyframes overlap, and a
/// place seen from ten keyframes should not weigh ten times.
const PCD_VOXEL_M: f64 = 0.1;

/// What writing a tile set produced.
#[derive(Debug, Clone)]
pub struct TileSetSummary {
    /// The index written.
    pub index: TileIndex,
    /// Bytes of the tile maps.
    pub map_bytes: u64,
    /// Bytes of the tiles' place grids (relocalization), summed.
    pub place_bytes: u64,
    /// Largest place grid as a share of its tile's file.
    pub worst_place_share: f64,
    /// The halo check, every tile's summed.
    pub halo_check: HaloCheck,
    /// The whole map, when it was kept ([`TileSetWriter::create`]'s `keep_merged`).
    pub merged: Option<WriteSummary>,
    /// Seconds finishing the tiles once every keyframe was written (grids cut, indexes,
    /// fsyncs, Autoware clouds, halo check).
    pub finish_seconds: f64,
}

/// Buffer of each tile's writer: hundreds are open at once, and a keyframe's segment
/// (tens of kilobytes and more) bypasses a buffer this size anyway.
const TILE_WRITE_BUFFER: usize = 64 << 10;

/// A tile being written: its file, its keyframes so far and how many are its own.
struct TileInProgress {
    writer: MapWriter,
    ids: Vec<KeyframeId>,
    core: u64,
}

/// A tile set written as the keyframes are baked (docs/DESIGN.md#notes-tiles): each
/// keyframe is serialized once and appended to the file of every tile holding it (its
/// core's and the halos it lies in), opened when its first keyframe comes; the whole
/// map's place grid and covisibility are gathered on the way, and each tile's part is
/// cut from them at [`finish`](Self::finish). No whole map is written unless kept, and
/// nothing is read back but each tile's own points for its Autoware cloud.
pub struct TileSetWriter {
    dir: PathBuf,
    geometry: TileGeometry,
    options: KeyframeMapOptions,
    map_from_input: Pose,
    /// The tile set being replaced, whose stale files go once the new one is complete.
    previous: Option<TileIndex>,
    /// The whole map's place grid, gathered from every keyframe.
    grid: GridBuilder,
    /// Every keyframe's id and pose, in order.
    poses: Vec<(KeyframeId, Pose)>,
    tiles: BTreeMap<(i32, i32), TileInProgress>,
    /// The whole map as `DIR/merged.kfmap`, when kept.
    merged: Option<MapWriter>,
    /// Tiles appended to since their writeback was last started, and the bytes.
    unsynced: (Vec<(i32, i32)>, u64),
}

/// Bytes appended over the tiles between starting their writeback: one tile's file
/// grows a few megabytes in all, too little to start its own, and leaving every tile's
/// writeback to its final fsync has the disk idle while the keyframes are built.
const TILES_WRITEBACK_STEP: u64 = 32 << 20;

impl TileSetWriter {
    /// Starts a tile set of maps with `options` in `dir` (created; a tile set already
    /// there is replaced once this one is finished, any other non-empty directory
    /// refused). `keep_merged` also writes the whole map as [`merged_map_path`].
    pub fn create(
        dir: &Path,
        geometry: TileGeometry,
        options: &KeyframeMapOptions,
        map_from_input: &Pose,
        keep_merged: bool,
    ) -> Result<Self, BakeError> {
        geometry.validate().map_err(BakeError::Tiles)?;
        let previous = prepare_directory(dir)?;
        let merged = if keep_merged {
            let mut writer = MapWriter::create(&merged_map_path(dir), options)?;
            writer.set_map_from_input(map_from_input);
            // The grid this writer gathers is the whole map's: built once, here.
            writer.expect_place_grid();
            Some(writer)
        } else {
            None
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            geometry,
            options: *options,
            map_from_input: *map_from_input,
            previous,
            grid: GridBuilder::new(&GridParams::default()),
            poses: Vec::new(),
            tiles: BTreeMap::new(),
            merged,
            unsynced: (Vec::new(), 0),
        })
    }

    /// Appends keyframes (ids ascending) to the tiles holding them: serialized and their
    /// part of the place grid found in parallel, appended in order.
    pub fn write_keyframes(&mut self, keyframes: &[Keyframe]) -> Result<(), BakeError> {
        let (grid, options) = (&self.grid, &self.options);
        let prepared: Vec<(SerializedKeyframe, GridContribution)> = keyframes
            .par_iter()
            .map(|k| {
                let serialized = SerializedKeyframe::new(k, options)?;
                Ok((serialized, grid.contribution(k.map_points()?)))
            })
            .collect::<Result<_, BakeError>>()?;
        for (keyframe, (serialized, place)) in keyframes.iter().zip(prepared) {
            self.append(keyframe, &serialized, place)?;
        }
        if self.unsynced.1 >= TILES_WRITEBACK_STEP {
            let (mut touched, _) = std::mem::take(&mut self.unsynced);
            touched.sort_unstable();
            touched.dedup();
            for key in touched {
                if let Some(tile) = self.tiles.get_mut(&key) {
                    tile.writer.write_back()?;
                }
            }
        }
        Ok(())
    }

    fn append(
        &mut self,
        keyframe: &Keyframe,
        serialized: &SerializedKeyframe,
        place: GridContribution,
    ) -> Result<(), BakeError> {
        let t = keyframe.pose.translation.vector;
        self.grid.add_anchor(t.into());
        self.grid.add(place);
        self.poses.push((keyframe.id, keyframe.pose));
        for (n, (col, row)) in self
            .geometry
            .tiles_holding(t.x, t.y)
            .into_iter()
            .enumerate()
        {
            let open = self.tiles.len();
            let tile = match self.tiles.entry((row, col)) {
                Entry::Occupied(e) => e.into_mut(),
                Entry::Vacant(e) => {
                    let path = self.dir.join(format!("{}.kfmap", tile_id(col, row)));
                    let mut writer =
                        MapWriter::create_buffered(&path, &self.options, TILE_WRITE_BUFFER)
                            .map_err(|e| open_tile_error(e, open))?;
                    writer.set_map_from_input(&self.map_from_input);
                    writer.expect_place_grid();
                    // The set is made durable at once, before its index (`finish`).
                    writer.leave_sync_to_caller();
                    e.insert(TileInProgress {
                        writer,
                        ids: Vec::new(),
                        core: 0,
                    })
                }
            };
            tile.writer.append_serialized(keyframe, serialized)?;
            self.unsynced.0.push((row, col));
            self.unsynced.1 += serialized.segment_bytes();
            tile.ids.push(keyframe.id);
            tile.core += u64::from(n == 0);
        }
        if let Some(merged) = &mut self.merged {
            merged.append_serialized(keyframe, serialized)?;
        }
        Ok(())
    }

    /// Finishes every tile owning a keyframe (a halo alone answers nothing: those files
    /// are dropped): its place grid cut from the whole map's, its part of `covis` and
    /// of the gravity `pool`, its Autoware cloud, the halo check; then the index, last.
    /// `progress(done, total)` after each tile.
    pub fn finish(
        self,
        next_id: u64,
        covis: &CovisSnapshot,
        pool: &[GravityRecord],
        progress: impl FnMut(usize, usize) + Send,
    ) -> Result<TileSetSummary, BakeError> {
        let started = Instant::now();
        let Self {
            dir,
            geometry,
            options,
            previous,
            grid,
            poses,
            mut tiles,
            merged,
            ..
        } = self;
        tiles.retain(|_, t| t.core > 0);
        // From the first tile renamed into place the old set is no longer whole: its
        // index goes first, so nothing serves a mix of the two.
        if previous.is_some() {
            std::fs::remove_file(dir.join(INDEX_FILE))
                .map_err(|e| BakeError::Io(IoError::os(dir.join(INDEX_FILE), e)))?;
        }
        // The whole map's voxels only: its levels are built for a kept merged map alone.
        let whole_voxels = match grid.marked_voxels(&GridParams::default()) {
            Ok(g) => Some(g),
            Err(e) => {
                tracing::warn!("tile set written without place grids (no relocalization): {e}");
                None
            }
        };
        let total = tiles.len();
        let mut index = TileIndex {
            format: INDEX_FORMAT,
            tile_size: geometry.tile_size,
            halo: geometry.halo,
            keyframes: poses.len() as u64,
            tiles: Vec::with_capacity(total),
            ranking: None,
        };
        let finishing = TileFinish {
            whole_voxels: whole_voxels.as_ref(),
            covis,
            pool,
            selection: options.selection,
            geometry,
            dir: &dir,
            near: NearIndex::new(&poses, geometry.halo.max(1.0)),
            poses: &poses,
            next_id,
        };
        // Tiles are independent: finished in parallel, each by one thread, the results
        // kept in tile order.
        let progress = Mutex::new((0, progress));
        let written: Vec<WrittenTile> = tiles
            .into_iter()
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|((row, col), tile)| {
                let written = finishing.tile(col, row, tile)?;
                if let Ok(mut guard) = progress.lock() {
                    let (done, report) = &mut *guard;
                    *done += 1;
                    report(*done, total);
                }
                Ok(written)
            })
            .collect::<Result<_, BakeError>>()?;
        let (mut map_bytes, mut place_bytes, mut worst_place_share) = (0, 0, 0.0_f64);
        let mut halo_check = HaloCheck::default();
        for tile in written {
            place_bytes += tile.place_bytes;
            worst_place_share =
                worst_place_share.max(tile.place_bytes as f64 / tile.entry.bytes.max(1) as f64);
            map_bytes += tile.entry.bytes;
            halo_check.add(&tile.halo_check);
            index.tiles.push(tile.entry);
        }
        let merged = match merged {
            Some(mut writer) => {
                writer.use_place_grid(whole_voxels.ok_or(GridError::Empty).and_then(|g| g.grid()));
                Some(writer.finish(next_id, covis, pool)?)
            }
            None => {
                // A whole map kept by an earlier bake would not be this set's.
                let _ = std::fs::remove_file(merged_map_path(&dir));
                None
            }
        };
        write_replacing(
            &dir.join(AUTOWARE_METADATA_FILE),
            index.autoware_metadata().as_bytes(),
        )?;
        // Every tile durable, then the index: a directory with an index is a complete
        // tile set (one file-system sync instead of one fsync per file).
        sync_file_system(&dir)?;
        write_atomic(&dir.join(INDEX_FILE), index.to_toml().as_bytes())?;
        remove_stale(&dir, previous, &index);
        Ok(TileSetSummary {
            index,
            map_bytes,
            place_bytes,
            worst_place_share,
            halo_check,
            merged,
            finish_seconds: started.elapsed().as_secs_f64(),
        })
    }
}

/// Opening a tile's file failed: past the open-files limit, say which and what to do.
fn open_tile_error(error: ArchiveError, open: usize) -> BakeError {
    match &error {
        ArchiveError::Io { message, .. } if message.contains("Too many open files") => {
            BakeError::Tiles(format!(
                "{error}: a tile set keeps every tile's file open while baking and {open} \
                 are; raise the open-files limit (ulimit -n) or use a larger --tile-size"
            ))
        }
        _ => error.into(),
    }
}

/// One tile written: its index entry, its place grid's bytes, its halo check.
struct WrittenTile {
    entry: TileEntry,
    place_bytes: u64,
    halo_check: HaloCheck,
}

/// What finishing a tile needs of the whole map.
struct TileFinish<'a> {
    /// The whole map's place-grid voxels, which every tile's grid is cut from.
    whole_voxels: Option<&'a MarkedVoxels>,
    /// The whole map's covisibility, which every tile keeps the part of among its
    /// keyframes.
    covis: &'a CovisSnapshot,
    pool: &'a [GravityRecord],
    selection: SelectionOptions,
    geometry: TileGeometry,
    dir: &'a Path,
    /// Every keyframe of the whole map by position.
    near: NearIndex,
    /// Every keyframe's pose, by id order.
    poses: &'a [(KeyframeId, Pose)],
    next_id: u64,
}

impl TileFinish<'_> {
    /// Finishes tile `(col, row)`: its place grid, covisibility and gravity records,
    /// its file, its Autoware point cloud, and checks its halo.
    fn tile(&self, col: i32, row: i32, tile: TileInProgress) -> Result<WrittenTile, BakeError> {
        let TileInProgress {
            mut writer,
            ids,
            core,
        } = tile;
        let geometry = self.geometry;
        let id = tile_id(col, row);
        let [x0, y0] = geometry.core_min(col, row);
        let own: Vec<(KeyframeId, Pose)> = ids
            .iter()
            .filter_map(|kf| {
                let at = self.poses.binary_search_by_key(kf, |(id, _)| *id).ok()?;
                Some(self.poses[at])
            })
            .collect();
        // The place grid is the whole map's within its reach of the core: a scan placed
        // in the core hits what it hits on the whole map, from whichever keyframes the
        // points came, and tries the same translations (docs/DESIGN.md#notes-tiles).
        // Relocalization searches around the core's keyframes: the halo's places are
        // the neighbours' to find.
        let mut search_region = None;
        let grid = match &self.whole_voxels {
            Some(whole_voxels) => {
                let reach = GridParams::default().reach;
                let searched: Vec<[f64; 3]> = own
                    .iter()
                    .map(|(_, p)| p.translation.vector)
                    .filter(|t| geometry.tile_of(t.x, t.y) == (col, row))
                    .map(Into::into)
                    .collect();
                let grid = whole_voxels.cut(
                    [x0 - reach, y0 - reach],
                    [
                        x0 + geometry.tile_size + reach,
                        y0 + geometry.tile_size + reach,
                    ],
                    &searched,
                );
                // The index carries every tile's region: each server's share of a search
                // over the set needs its neighbours' (`SearchShare`).
                search_region = grid.as_ref().ok().map(|g| g.region);
                grid
            }
            None => Err(GridError::Empty),
        };
        writer.use_place_grid(grid);
        let pool: Vec<_> = self
            .pool
            .iter()
            .filter(|g| ids.binary_search(&g.keyframe).is_ok())
            .cloned()
            .collect();
        let covis = self.covis.restricted_to(&ids);
        let file = format!("{id}.kfmap");
        let written = writer.finish(self.next_id, &covis, &pool)?;
        let everyone = (&self.near, self.poses);
        let halo_check = check_halo(&own, everyone, geometry, (col, row), &self.selection);
        let pcd = format!("{id}.pcd");
        let cloud = core_cloud(&self.dir.join(&file), geometry, (col, row))
            .map_err(|e| BakeError::Tiles(format!("tile {id}: its Autoware cloud: {e}")))?;
        write_replacing(&self.dir.join(&pcd), &write_pcd(&cloud, PcdData::Binary))?;
        Ok(WrittenTile {
            entry: TileEntry {
                id,
                col,
                row,
                file,
                pcd,
                keyframes: written.keyframes as u64,
                core_keyframes: core,
                points: written.points,
                bytes: written.bytes,
                search_min: search_region.map(|r| r.min),
                search_max: search_region.map(|r| r.max),
            },
            place_bytes: written.place_bytes,
            halo_check,
        })
    }
}

/// Tile `(col, row)`'s core points from its finished file, thinned to [`PCD_VOXEL_M`]
/// (read back from the page cache: gathering them while baking would hold every
/// tile's points at once).
fn core_cloud(
    file: &Path,
    geometry: TileGeometry,
    (col, row): (i32, i32),
) -> Result<PointCloud, Box<dyn std::error::Error>> {
    // Written a moment ago by this bake: the archives' structure is not checked again
    // (their checksums still are).
    let trusted = OpenOptions {
        trust: true,
        ..OpenOptions::default()
    };
    let opened = open_map(file, trusted)?;
    let [x0, y0] = geometry.core_min(col, row);
    let s = geometry.tile_size;
    let in_core = |p: &[f64; 3]| p[0] >= x0 && p[0] < x0 + s && p[1] >= y0 && p[1] < y0 + s;
    let mut core_points: Vec<[f32; 3]> = Vec::new();
    for keyframe in opened.map.keyframes() {
        core_points.extend(
            keyframe
                .map_points()?
                .iter()
                .filter(|p| in_core(p))
                .map(|p| p.map(|v| v as f32)),
        );
    }
    Ok(PointCloud::from_points(core_points).voxel_downsample(PCD_VOXEL_M)?)
}

/// What a tile cut's halo check found: of the guesses sampled (each tile's core
/// keyframes' poses, and each moved half the halo along x and y, where the router still
/// sends a guess to the tile), how many select from their tile's keyframes what they
/// select from the whole map's.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HaloCheck {
    /// Guesses sampled.
    pub sampled: usize,
    /// Those whose active set (what a registration pairs with) is the whole map's.
    pub active_agree: usize,
    /// Those whose [`SURROUNDINGS`] keyframes nearest by position (what the tracker's
    /// explained share searches) are the whole map's.
    pub surroundings_agree: usize,
}

impl HaloCheck {
    fn add(&mut self, other: &Self) {
        self.sampled += other.sampled;
        self.active_agree += other.active_agree;
        self.surroundings_agree += other.surroundings_agree;
    }
}

/// The halo check of one tile ([`HaloCheck`]): the keyframes selected from the tile's
/// keyframes `own` against those selected from the whole map's (`near`: its keyframes
/// by position; `every`: all of them), for the active set (`selection`) and the
/// surroundings.
fn check_halo(
    own: &[(KeyframeId, Pose)],
    (near, every): (&NearIndex, &[(KeyframeId, Pose)]),
    geometry: TileGeometry,
    (col, row): (i32, i32),
    selection: &SelectionOptions,
) -> HaloCheck {
    let h = geometry.halo / 2.0;
    let mut samples = Vec::new();
    for (_, pose) in own {
        let t = pose.translation.vector;
        if geometry.distance_to_core(col, row, t.x, t.y) > 0.0 {
            continue;
        }
        for (dx, dy) in [(0.0, 0.0), (h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)] {
            if geometry.distance_to_core(col, row, t.x + dx, t.y + dy) <= h {
                let mut q = *pose;
                q.translation.vector += nalgebra::Vector3::new(dx, dy, 0.0);
                samples.push(q);
            }
        }
    }
    let surroundings = SelectionOptions::by_position(SURROUNDINGS);
    let (active_agree, surroundings_agree) = samples
        .par_iter()
        .map(|q| {
            let agrees = |selection: &SelectionOptions| {
                let mut from_tile = select_active(own, q, selection);
                // Whatever the whole map selects lies within `reach` (see `NearIndex`);
                // a tile with no more keyframes than it selects bounds nothing, and is
                // compared with every keyframe of the map.
                let mut from_whole = match selection_reach(own, q, selection) {
                    Some(reach) => select_active(&near.within(q, reach), q, selection),
                    None => select_active(every, q, selection),
                };
                from_tile.sort_unstable();
                from_whole.sort_unstable();
                from_tile == from_whole
            };
            (
                usize::from(agrees(selection)),
                usize::from(agrees(&surroundings)),
            )
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    HaloCheck {
        sampled: samples.len(),
        active_agree,
        surroundings_agree,
    }
}

/// How far from `q` the whole map's selection can reach, given that a subset `own`
/// selects as it does: the whole map's primary slots rank at least as well, so lie
/// within the subset's worst primary metric `m` (metric >= distance); its diverse slots
/// within `3 m` (the near pool's bound) or, falling back, the first unselected in
/// metric order, which for the `j`-th diverse slot ranks at most `primaries + j` in the
/// whole map, so within the subset's metric at that rank: its last slot's at most.
/// `None` when the subset has fewer keyframes than the selection takes (it selects all
/// it has, which only every keyframe of the map can be compared with).
fn selection_reach(
    own: &[(KeyframeId, Pose)],
    q: &Pose,
    selection: &SelectionOptions,
) -> Option<f64> {
    let ranked = rank(own, q, selection);
    let slots = selection.max_search_keyframes;
    if slots == 0 || ranked.len() < slots {
        return None;
    }
    let primaries = slots - selection.num_diverse_keyframes.min(slots - 1);
    let worst_primary = ranked[primaries - 1].metric;
    let last_slot = ranked[slots - 1].metric;
    Some((3.0 * worst_primary).max(1.0).max(last_slot))
}

/// The whole map's keyframes by position, in square cells, for "every keyframe within
/// r of q".
struct NearIndex {
    cell: f64,
    cells: std::collections::HashMap<(i64, i64), Vec<(KeyframeId, Pose)>>,
}

impl NearIndex {
    fn new(keyframes: &[(KeyframeId, Pose)], cell: f64) -> Self {
        let mut cells: std::collections::HashMap<(i64, i64), Vec<(KeyframeId, Pose)>> =
            Default::default();
        for &(id, pose) in keyframes {
            let t = pose.translation.vector;
            cells
                .entry(((t.x / cell).floor() as i64, (t.y / cell).floor() as i64))
                .or_default()
                .push((id, pose));
        }
        Self { cell, cells }
    }

    /// Keyframes within `r` (in x-y, then exactly in 3D) of `q`, ascending id.
    fn within(&self, q: &Pose, r: f64) -> Vec<(KeyframeId, Pose)> {
        let t = q.translation.vector;
        let lo = |v: f64| ((v - r) / self.cell).floor() as i64;
        let hi = |v: f64| ((v + r) / self.cell).floor() as i64;
        let mut found = Vec::new();
        for cx in lo(t.x)..=hi(t.x) {
            for cy in lo(t.y)..=hi(t.y) {
                if let Some(list) = self.cells.get(&(cx, cy)) {
                    found.extend(
                        list.iter()
                            .filter(|(_, p)| (p.translation.vector - t).norm() <= r)
                            .copied(),
                    );
                }
            }
        }
        found.sort_unstable_by_key(|(id, _)| *id);
        found
    }
}

/// Creates `dir`, or accepts it empty or holding a tile set (whose index is returned, so
/// its files can be removed once the new set is written).
fn prepare_directory(dir: &Path) -> Result<Option<TileIndex>, BakeError> {
    let io = |e: std::io::Error| BakeError::Io(IoError::os(dir, e));
    if !dir.exists() {
        std::fs::create_dir_all(dir).map_err(io)?;
        return Ok(None);
    }
    if !dir.is_dir() {
        return Err(BakeError::Tiles(format!(
            "{}: not a directory (a tile set is a directory of tiles)",
            dir.display()
        )));
    }
    if dir.join(INDEX_FILE).exists() {
        return Ok(Some(TileIndex::load(dir)?));
    }
    // The merged map `kfmap bake --tile-size` writes first may be there.
    let empty = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(Result::ok)
        .all(|e| e.path() == merged_map_path(dir));
    if !empty {
        return Err(BakeError::Tiles(format!(
            "{}: not empty and not a tile set (no {INDEX_FILE}); give a new or empty directory",
            dir.display()
        )));
    }
    Ok(None)
}

/// Removes the files of the tile set `previous` that the new `index` no longer lists.
fn remove_stale(dir: &Path, previous: Option<TileIndex>, index: &TileIndex) {
    let Some(previous) = previous else { return };
    let kept: HashSet<&str> = index
        .tiles
        .iter()
        .flat_map(|t| [t.file.as_str(), t.pcd.as_str()])
        .collect();
    for t in &previous.tiles {
        for name in [&t.file, &t.pcd] {
            if !kept.contains(name.as_str()) {
                let _ = std::fs::remove_file(dir.join(name));
            }
        }
    }
}

/// The merged map a tile set was cut from, when `kfmap bake --tile-size --keep-merged`
/// kept it: `DIR/merged.kfmap`.
pub fn merged_map_path(dir: &Path) -> PathBuf {
    dir.join("merged.kfmap")
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_map::place::PlaceGrid;
    use nalgebra::Vector3;

    /// Keyframes spread over a `side` x `side` square (an R2 low-discrepancy sequence),
    /// each with its own heading.
    fn spread(count: usize, side: f64) -> Vec<(KeyframeId, Pose)> {
        let fraction = |v: f64| v - v.floor();
        (0..count)
            .map(|i| {
                let n = i as f64 + 1.0;
                let t = Vector3::new(
                    fraction(n * 0.754_877_666_2) * side,
                    fraction(n * 0.569_840_290_9) * side,
                    0.0,
                );
                let yaw = (fraction(n * 0.618_033_988_7) - 0.5) * std::f64::consts::TAU;
                (i as KeyframeId, Pose::new(t, Vector3::new(0.0, 0.0, yaw)))
            })
            .collect()
    }

    /// The keyframes `selection` takes from `set` at `q`, ascending id: over every
    /// keyframe given, with no spatial index and no reach bound (what the check saves).
    fn brute_force(
        set: &[(KeyframeId, Pose)],
        q: &Pose,
        selection: &SelectionOptions,
    ) -> Vec<KeyframeId> {
        let mut ids = select_active(set, q, selection);
        ids.sort_unstable();
        ids
    }

    /// Tile `tile`'s halo check, asserted equal to brute force: every sampled guess's
    /// active set and surroundings from the tile's keyframes against those from every
    /// keyframe of the map.
    fn check_by_brute_force(
        keyframes: &[(KeyframeId, Pose)],
        geometry: TileGeometry,
        tile: (i32, i32),
        selection: &SelectionOptions,
    ) -> HaloCheck {
        let near = NearIndex::new(keyframes, geometry.halo.max(1.0));
        let own: Vec<(KeyframeId, Pose)> = keyframes
            .iter()
            .filter(|(_, p)| {
                let t = p.translation.vector;
                geometry.tiles_holding(t.x, t.y).contains(&tile)
            })
            .copied()
            .collect();
        let check = check_halo(&own, (&near, keyframes), geometry, tile, selection);
        let h = geometry.halo / 2.0;
        let mut expected = HaloCheck::default();
        let surroundings = SelectionOptions::by_position(SURROUNDINGS);
        for (_, pose) in &own {
            let t = pose.translation.vector;
            if geometry.tile_of(t.x, t.y) != tile {
                continue;
            }
            for (dx, dy) in [(0.0, 0.0), (h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)] {
                if geometry.distance_to_core(tile.0, tile.1, t.x + dx, t.y + dy) > h {
                    continue;
                }
                let mut q = *pose;
                q.translation.vector += Vector3::new(dx, dy, 0.0);
                let agrees = |s: &SelectionOptions| {
                    brute_force(&own, &q, s) == brute_force(keyframes, &q, s)
                };
                expected.sampled += 1;
                expected.active_agree += usize::from(agrees(selection));
                expected.surroundings_agree += usize::from(agrees(&surroundings));
            }
        }
        assert_eq!(check, expected, "halo {} m, tile {tile:?}", geometry.halo);
        check
    }

    /// The halo check against brute force ([`check_by_brute_force`]) on 600 keyframes
    /// in 20 m tiles, and how it tells halos apart.
    #[test]
    fn the_halo_check_counts_what_selection_over_the_whole_map_finds() {
        let keyframes = spread(600, 60.0);
        let selection = SelectionOptions::default();
        let mut per_halo = Vec::new();
        for halo in [1.0, 3.0, 15.0] {
            let geometry = TileGeometry {
                tile_size: 20.0,
                halo,
            };
            let mut sum = HaloCheck::default();
            for tile in [(0, 0), (1, 1), (2, 0), (1, 2)] {
                sum.add(&check_by_brute_force(
                    &keyframes, geometry, tile, &selection,
                ));
            }
            per_halo.push((halo, sum.active_agree, sum.surroundings_agree, sum.sampled));
        }
        // Agreement grows with the halo, from a 1 m halo that misses keyframes the
        // whole map would use to a 15 m one that holds nearly all (measured: active
        // sets 1046, 1250 and 1340 of 1345 guesses, surroundings 1026, 1265 and 1345).
        println!("(halo, active agree, surroundings agree, sampled): {per_halo:?}");
        for column in [1, 2] {
            let agree: Vec<usize> = per_halo
                .iter()
                .map(|h| if column == 1 { h.1 } else { h.2 })
                .collect();
            assert!(agree[0] < agree[1] && agree[1] < agree[2], "{per_halo:?}");
        }
        let (_, wide_agree, wide_around, wide_sampled) = per_halo[2];
        assert!(wide_agree * 100 >= wide_sampled * 99, "{per_halo:?}");
        assert!(wide_around * 100 >= wide_sampled * 99, "{per_halo:?}");
    }

    /// Tiles holding no more keyframes than a selection takes are compared with every
    /// keyframe of the map (they bound nothing), and a selection with two diverse slots
    /// that fall back past the near pool is bounded by the tile's last slot: both
    /// against brute force, on 14 keyframes over 60 m in 20 m tiles.
    #[test]
    fn sparse_tiles_and_two_diverse_slots_are_checked_against_the_whole_map() {
        let keyframes = spread(14, 60.0);
        let two_diverse = SelectionOptions {
            max_search_keyframes: 4,
            num_diverse_keyframes: 2,
            rotation_distance_weight: 2.0,
        };
        let (mut sparse_tiles, mut sum) = (0, HaloCheck::default());
        for halo in [2.0, 10.0, 30.0] {
            let geometry = TileGeometry {
                tile_size: 20.0,
                halo,
            };
            for col in 0..3 {
                for row in 0..3 {
                    let held = keyframes
                        .iter()
                        .filter(|(_, p)| {
                            let t = p.translation.vector;
                            geometry.tiles_holding(t.x, t.y).contains(&(col, row))
                        })
                        .count();
                    sparse_tiles += usize::from(held > 0 && held <= SURROUNDINGS);
                    for selection in [SelectionOptions::default(), two_diverse] {
                        sum.add(&check_by_brute_force(
                            &keyframes,
                            geometry,
                            (col, row),
                            &selection,
                        ));
                    }
                }
            }
        }
        println!("{sparse_tiles} sparse tiles; {sum:?}");
        // The cases the test is for happened: tiles with few keyframes, and guesses
        // whose tile selects otherwise than the whole map.
        assert!(sparse_tiles > 0);
        assert!(sum.surroundings_agree < sum.sampled && sum.active_agree < sum.sampled);
    }

    /// Two diverse slots, the second falling back past the near pool (1 m) to the next
    /// keyframe in metric order: the reach holds it, so a tile holding every keyframe
    /// selects from its neighbourhood what the whole map selects.
    #[test]
    fn the_reach_holds_a_diverse_slot_that_falls_back() {
        let at = |x: f64| Pose::new(Vector3::new(x, 0.0, 0.0), Vector3::zeros());
        let keyframes: Vec<(KeyframeId, Pose)> = [0.1, 0.5, 5.0, 10.0]
            .into_iter()
            .enumerate()
            .map(|(i, x)| (i as KeyframeId, at(x)))
            .collect();
        let selection = SelectionOptions {
            max_search_keyframes: 3,
            num_diverse_keyframes: 2,
            rotation_distance_weight: 2.0,
        };
        let q = at(0.0);
        let whole = select_active(&keyframes, &q, &selection);
        assert_eq!(whole, vec![0, 1, 2]);
        let reach = selection_reach(&keyframes, &q, &selection).expect("four keyframes bound it");
        let near = NearIndex::new(&keyframes, 1.0);
        assert_eq!(
            select_active(&near.within(&q, reach), &q, &selection),
            whole
        );
    }

    /// A synthetic scan in the sensor frame: ground, two walls and posts within 12 m.
    fn scan(seed: u64) -> PointCloud {
        let mut state = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
        let mut next = move |low: f32, high: f32| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            low + (high - low) * ((state >> 40) as f32 / (1u64 << 24) as f32)
        };
        let points = (0..1500)
            .map(|i| match i % 3 {
                0 => [next(-12.0, 12.0), next(-12.0, 12.0), next(-0.02, 0.02)],
                1 => [
                    next(-12.0, 12.0),
                    if i % 2 == 0 { -6.0 } else { 7.0 },
                    next(0.0, 3.0),
                ],
                _ => [
                    next(-12.0, 12.0).round(),
                    next(-5.0, 6.0).round(),
                    next(0.0, 2.0),
                ],
            })
            .collect();
        PointCloud::from_points(points)
    }

    /// A tile set streamed by [`TileSetWriter`] against independent oracles: its whole
    /// map byte-identical to the one `MapWriter` bakes from the same keyframes; each
    /// tile's keyframes by brute-force membership, each byte-identical to the whole
    /// map's; each tile's grid the whole map's cut to the tile; covisibility edges the
    /// whole map's among a tile's keyframes; the Autoware cloud inside its core.
    #[test]
    fn a_streamed_tile_set_holds_what_the_whole_map_holds() {
        let dir = std::env::temp_dir().join(format!("kfmap-tiling-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let options = KeyframeMapOptions::default();
        let keyframes: Vec<Keyframe> = spread(60, 55.0)
            .into_iter()
            .map(|(id, pose)| {
                Keyframe::build(id, pose, id as f64, scan(id), &options.covariance).unwrap()
            })
            .collect();
        let mut covis = kfmap_map::covis::CovisibilityGraph::new(options.covisibility);
        for k in &keyframes {
            covis.set_keyframe(k.id, k.map_points().unwrap());
        }
        let covis = covis.snapshot();
        let level = Pose::new(Vector3::new(0.5, -1.0, 0.0), Vector3::zeros());
        let whole_path = dir.join("whole.kfmap");
        let mut whole = MapWriter::create(&whole_path, &options).unwrap();
        whole.set_map_from_input(&level);
        for chunk in keyframes.chunks(7) {
            whole.write_keyframes(chunk).unwrap();
        }
        whole.finish(60, &covis, &[]).unwrap();

        let geometry = TileGeometry {
            tile_size: 20.0,
            halo: 6.0,
        };
        let tiles = dir.join("tiles");
        let mut writer = TileSetWriter::create(&tiles, geometry, &options, &level, true).unwrap();
        for chunk in keyframes.chunks(5) {
            writer.write_keyframes(chunk).unwrap();
        }
        let set = writer.finish(60, &covis, &[], |_, _| {}).unwrap();
        assert_eq!(
            std::fs::read(merged_map_path(&tiles)).unwrap(),
            std::fs::read(&whole_path).unwrap(),
            "the kept whole map is the one MapWriter writes"
        );
        let whole = open_map(&whole_path, OpenOptions::default()).unwrap();
        let whole_grid = whole.place.as_ref().unwrap().view().unwrap();
        let (s, h) = (geometry.tile_size, geometry.halo);
        let mut owned = 0;
        for entry in &set.index.tiles {
            let (x0, y0) = (f64::from(entry.col) * s, f64::from(entry.row) * s);
            let (mut core, mut all) = (Vec::new(), Vec::new());
            for k in &keyframes {
                let t = k.pose.translation.vector;
                if t.x >= x0 && t.x < x0 + s && t.y >= y0 && t.y < y0 + s {
                    core.push(k.id);
                }
                if t.x >= x0 - h && t.x <= x0 + s + h && t.y >= y0 - h && t.y <= y0 + s + h {
                    all.push(k.id);
                }
            }
            assert!(!core.is_empty(), "tile {} owns nothing", entry.id);
            owned += core.len();
            assert_eq!(
                entry.core_keyframes as usize,
                core.len(),
                "tile {}",
                entry.id
            );
            let tile = open_map(&tiles.join(&entry.file), OpenOptions::default()).unwrap();
            let ids: Vec<KeyframeId> = tile.index.keyframes.iter().map(|k| k.id).collect();
            assert_eq!(ids, all, "tile {}", entry.id);
            for k in &tile.index.keyframes {
                let w = whole.index.keyframes.iter().find(|w| w.id == k.id).unwrap();
                assert_eq!((k.checksum, k.len, k.pose), (w.checksum, w.len, w.pose));
            }
            let edges: Vec<_> = whole
                .index
                .covis_edges
                .iter()
                .filter(|(a, b, _)| all.contains(a) && all.contains(b))
                .copied()
                .collect();
            assert_eq!(tile.index.covis_edges, edges, "tile {}", entry.id);
            assert_eq!(tile.index.map_from_input, whole.index.map_from_input);
            // The grid: the whole map's voxels within the grid's reach of the core.
            let searched: Vec<[f64; 3]> = keyframes
                .iter()
                .filter(|k| core.contains(&k.id))
                .map(|k| k.pose.translation.vector.into())
                .collect();
            let reach = GridParams::default().reach;
            let expected = PlaceGrid::cut_from(
                &whole_grid,
                [x0 - reach, y0 - reach],
                [x0 + s + reach, y0 + s + reach],
                &searched,
            )
            .unwrap();
            let expected = expected.view();
            let got = tile.place.as_ref().unwrap().view().unwrap();
            assert_eq!(
                (got.origin(), got.dims(), got.region()),
                (expected.origin(), expected.dims(), expected.region()),
                "tile {}",
                entry.id
            );
            let dims = got.dims();
            let mut marked = 0;
            for x in 0..dims[0] {
                for y in 0..dims[1] {
                    for z in 0..dims[2] {
                        let v = [x, y, z];
                        assert_eq!(got.marked(0, v), expected.marked(0, v), "{v:?}");
                        marked += usize::from(got.marked(0, v));
                    }
                }
            }
            assert!(marked > 0, "tile {}: an empty grid", entry.id);
            let pcd_path = tiles.join(&entry.pcd);
            let bytes = std::fs::read(&pcd_path).unwrap();
            let (cloud, _, _) = kfmap_geometry::io::read_pcd(&pcd_path, &bytes).unwrap();
            assert!(!cloud.points.is_empty(), "tile {}", entry.id);
            for p in &cloud.points {
                let (x, y) = (f64::from(p[0]), f64::from(p[1]));
                assert!(x >= x0 - 0.1 && x < x0 + s + 0.1 && y >= y0 - 0.1 && y < y0 + s + 0.1);
            }
        }
        assert_eq!(owned, keyframes.len(), "every keyframe in exactly one core");
        assert!(
            set.index.tiles.len() >= 6,
            "{} tiles",
            set.index.tiles.len()
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
