//! The served map and its atomic replacement on reload: requests in flight keep the
//! map they started with (an `Arc`), new requests get the new one.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock, RwLock};

use kfmap_map::archive::{ArchiveError, BakedPlaceGrid, OpenOptions, open_map};
use kfmap_map::map::KeyframeMap;
use kfmap_map::place::{GridView, OwnedColumns};
use kfmap_map::tiles::SearchShare;

/// A loaded map.
pub struct ServedMap {
    /// The map, reading keyframes from the memory-mapped file.
    pub map: KeyframeMap,
    /// The file it came from.
    pub path: PathBuf,
    /// Counts loads: 0 for the first map, +1 per reload.
    pub generation: u64,
    /// Keyframes in the map.
    pub keyframes: usize,
    /// Points in the map.
    pub points: usize,
    /// `T_map_input`: how bake moved the input poses into the map frame.
    pub map_from_input: [f64; 7],
    /// True when the map was baked to serve exact cov2cov by default (`[map]
    /// cov2cov-mode = "exact"`); the map itself is opened in approximate mode and
    /// exact requests build their merged submaps per session.
    pub exact_by_default: bool,
    /// The place grid of relocalization; `None` for maps baked without one.
    pub place: Option<BakedPlaceGrid>,
    /// A tile's share of a relocalization over its tile set (`serve --tiles`): the
    /// translations its places phase tries. `None` for a whole map.
    pub search_share: Option<SearchShare>,
    /// `search_share` over the place grid's lattice, built on first use.
    share_columns: OnceLock<OwnedColumns>,
}

impl ServedMap {
    /// Memory-maps `path`; nothing is rebuilt.
    pub fn open(path: &Path, trust: bool, generation: u64) -> Result<Self, ArchiveError> {
        let opened = open_map(
            path,
            OpenOptions {
                trust,
                approximate_cov: true,
            },
        )?;
        let map = opened.map;
        Ok(Self {
            place: opened.place,
            exact_by_default: map.options().serve_exact,
            map_from_input: opened.index.map_from_input,
            keyframes: map.len(),
            points: map.point_count(),
            map,
            path: path.to_path_buf(),
            generation,
            search_share: None,
            share_columns: OnceLock::new(),
        })
    }

    /// The columns of `grid`'s search region (this map's place grid) in this tile's
    /// share; `None` for a whole map.
    pub fn share_columns(&self, grid: &GridView<'_>) -> Option<&OwnedColumns> {
        let share = self.search_share.as_ref()?;
        Some(self.share_columns.get_or_init(|| {
            OwnedColumns::new(&grid.region(), grid.resolution(), |x, y| share.owns(x, y))
        }))
    }
}

/// The current map, swapped atomically on reload.
pub struct MapSlot {
    current: RwLock<Arc<ServedMap>>,
}

impl MapSlot {
    /// A slot holding `map`.
    pub fn new(map: ServedMap) -> Self {
        Self {
            current: RwLock::new(Arc::new(map)),
        }
    }

    /// The map new requests use.
    pub fn current(&self) -> Arc<ServedMap> {
        self.current
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Opens `path` (the current file when `None`) and switches to it; on failure the
    /// current map stays.
    pub fn reload(&self, path: Option<&Path>, trust: bool) -> Result<Arc<ServedMap>, ArchiveError> {
        let old = self.current();
        let path = path.unwrap_or(&old.path);
        let mut new = ServedMap::open(path, trust, old.generation + 1)?;
        new.search_share = old.search_share.clone();
        let new = Arc::new(new);
        *self.current.write().unwrap_or_else(|e| e.into_inner()) = new.clone();
        Ok(new)
    }
}
