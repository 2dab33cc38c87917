//! Tile sets: a map cut into square tiles on the map frame's x-y grid, each a `.kfmap` of
//! its own holding the keyframes of its *core* square plus every keyframe within the
//! *halo* around it (docs/DESIGN.md#notes-tiles). A request whose pose guess lies in a
//! tile's core is answered by that tile alone, from the same keyframes the whole map
//! would use, so no answer is ever merged across servers.
//!
//! The index (`tiles.toml`) names every tile, its file and its square; Autoware's
//! `pointcloud_map_metadata.yaml` lists the tiles' point clouds (`<id>.pcd`, core square
//! only, no overlap) for its map loader. Tile `(col, row)` covers
//! `[col s, (col + 1) s) x [row s, (row + 1) s)` for tile size `s`; its id is
//! `x<col>_y<row>` (a valid Zenoh key chunk: remote clients address tiles by it).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

mod share;
pub use share::SearchShare;

/// The index file of a tile set, in its directory.
pub const INDEX_FILE: &str = "tiles.toml";
/// Autoware's metadata of a divided point-cloud map, beside the index.
pub const AUTOWARE_METADATA_FILE: &str = "pointcloud_map_metadata.yaml";
/// The index format this build reads and writes.
pub const INDEX_FORMAT: u32 = 1;
/// Most tiles one index may list (a 1000 km^2 site in 250 m tiles is 16 000).
pub const MAX_TILES: usize = 1 << 20;
/// Largest index file read, bytes (about 200 bytes a tile).
const MAX_INDEX_BYTES: u64 = 256 << 20;

/// Why a tile set cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TileError {
    /// The index could not be read.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
    /// The index is not a valid tile index.
    #[error("{path}: {message}")]
    Invalid {
        /// The file (or the tile set's directory).
        path: PathBuf,
        /// What is wrong, naming the field or tile.
        message: String,
    },
    /// A tile asked for that the index does not list.
    #[error("tile {id:?} is not in the tile set {dir} (it lists {listed})")]
    Unknown {
        /// The id asked for.
        id: String,
        /// The tile set's directory.
        dir: PathBuf,
        /// Some of the ids it lists.
        listed: String,
    },
}

/// How a map is cut.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileGeometry {
    /// Edge of a tile's core square, metres.
    pub tile_size: f64,
    /// Keyframes this far outside a core square (per axis) also go into its tile, metres.
    pub halo: f64,
}

impl TileGeometry {
    /// Checks the values; the error names the option.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.tile_size.is_finite() && (1.0..=100_000.0).contains(&self.tile_size)) {
            return Err(format!(
                "tile-size {} is out of range: 1 to 100000 m",
                self.tile_size
            ));
        }
        if !(self.halo.is_finite() && self.halo >= 0.0 && self.halo <= 4.0 * self.tile_size) {
            return Err(format!(
                "halo {} is out of range: 0 m to 4 times the tile size",
                self.halo
            ));
        }
        Ok(())
    }

    /// The tile whose core holds map-frame `(x, y)`.
    pub fn tile_of(&self, x: f64, y: f64) -> (i32, i32) {
        let cell = |v: f64| {
            (v / self.tile_size)
                .floor()
                .clamp(i32::MIN as f64, i32::MAX as f64)
        };
        (cell(x) as i32, cell(y) as i32)
    }

    /// Low corner of tile `(col, row)`'s core square.
    pub fn core_min(&self, col: i32, row: i32) -> [f64; 2] {
        [
            f64::from(col) * self.tile_size,
            f64::from(row) * self.tile_size,
        ]
    }

    /// Every tile whose core square grown by the halo holds `(x, y)`: the tiles a
    /// keyframe there belongs to (its core tile first).
    pub fn tiles_holding(&self, x: f64, y: f64) -> Vec<(i32, i32)> {
        let core = self.tile_of(x, y);
        let mut tiles = vec![core];
        let (low, high) = (
            self.tile_of(x - self.halo, y - self.halo),
            self.tile_of(x + self.halo, y + self.halo),
        );
        for row in low.1..=high.1 {
            for col in low.0..=high.0 {
                if (col, row) != core && self.distance_to_core(col, row, x, y) <= self.halo {
                    tiles.push((col, row));
                }
            }
        }
        tiles
    }

    /// Chebyshev distance from `(x, y)` to tile `(col, row)`'s core square (0 inside).
    pub fn distance_to_core(&self, col: i32, row: i32, x: f64, y: f64) -> f64 {
        let [x0, y0] = self.core_min(col, row);
        let s = self.tile_size;
        let outside = |v: f64, low: f64| (low - v).max(v - (low + s)).max(0.0);
        outside(x, x0).max(outside(y, y0))
    }
}

/// A tile's id: `x<col>_y<row>`.
pub fn tile_id(col: i32, row: i32) -> String {
    format!("x{col}_y{row}")
}

/// One tile of the index.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct TileEntry {
    /// `x<col>_y<row>`.
    pub id: String,
    /// Column: the core square starts at `col * tile-size` on x.
    pub col: i32,
    /// Row: the core square starts at `row * tile-size` on y.
    pub row: i32,
    /// The tile's map, a file name in the tile set's directory.
    pub file: String,
    /// The core square's points for Autoware (`<id>.pcd`), a file name beside it.
    pub pcd: String,
    /// Keyframes in the tile's map (core and halo).
    pub keyframes: u64,
    /// Of them, keyframes in the core square.
    pub core_keyframes: u64,
    /// Map points in the tile's map.
    pub points: u64,
    /// The tile map's file size, bytes.
    pub bytes: u64,
    /// Low corner of the translations its relocalization search tries (its place
    /// grid's region, the grid's levelled frame, metres); with `search-max`, what
    /// [`SearchShare`] splits among the tiles. Absent in cuts by older kfmap.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub search_min: Option<[f64; 3]>,
    /// High corner; see `search-min`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub search_max: Option<[f64; 3]>,
}

/// `tiles.toml`: the tile set's geometry and tiles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct TileIndex {
    /// [`INDEX_FORMAT`].
    pub format: u32,
    /// Edge of a core square, metres.
    pub tile_size: f64,
    /// Halo around each core square, metres.
    pub halo: f64,
    /// Keyframes of the map cut (each in exactly one core).
    pub keyframes: u64,
    /// The tiles, by row then column.
    #[serde(rename = "tile", default)]
    pub tiles: Vec<TileEntry>,
    /// How the tiles' servers rank places (their `[relocalize]` settings), as a gateway
    /// publishes the index; absent in `tiles.toml` (the servers' config decides).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ranking: Option<PlaceRanking>,
}

/// The servers' `[relocalize]` settings a client merging every tile's relocalization
/// needs to rank places as one search of the merged map would: which places the search
/// keeps (`keep-ratio`, the separation), and when the best is `ambiguous` (the margin,
/// what counts as another place). A gateway reads them from its servers' status and
/// publishes them with the tile index, so a site whose `server.toml` changes them is
/// ranked by its clients as its servers rank.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct PlaceRanking {
    /// `[relocalize.search] keep-ratio`.
    pub keep_ratio: f64,
    /// `[relocalize.search] separation-m`.
    pub separation_m: f64,
    /// `[relocalize.search] separation-deg`.
    pub separation_deg: f64,
    /// `[relocalize] ambiguity-margin`.
    pub ambiguity_margin: f64,
    /// `[relocalize] distinct-m`.
    pub distinct_m: f64,
    /// `[relocalize] distinct-deg`.
    pub distinct_deg: f64,
}

impl PlaceRanking {
    /// The ranking settings of `params`.
    pub fn of(params: &crate::place::RelocalizeParams) -> Self {
        Self {
            keep_ratio: params.search.keep_ratio,
            separation_m: params.search.separation_m,
            separation_deg: params.search.separation_deg,
            ambiguity_margin: params.ambiguity_margin,
            distinct_m: params.distinct_m,
            distinct_deg: params.distinct_deg,
        }
    }

    /// `params` with these ranking settings.
    pub fn applied_to(
        &self,
        mut params: crate::place::RelocalizeParams,
    ) -> crate::place::RelocalizeParams {
        params.search.keep_ratio = self.keep_ratio;
        params.search.separation_m = self.separation_m;
        params.search.separation_deg = self.separation_deg;
        params.ambiguity_margin = self.ambiguity_margin;
        params.distinct_m = self.distinct_m;
        params.distinct_deg = self.distinct_deg;
        params
    }

    /// The settings are usable: the server's own checks of them
    /// ([`crate::place::RelocalizeParams::validate`]), the message naming the option.
    pub fn validate(&self) -> Result<(), String> {
        self.applied_to(crate::place::RelocalizeParams::default())
            .validate()
            .map_err(|e| format!("ranking: {e}"))
    }
}

impl Default for PlaceRanking {
    fn default() -> Self {
        Self::of(&crate::place::RelocalizeParams::default())
    }
}

impl TileIndex {
    /// The geometry.
    pub fn geometry(&self) -> TileGeometry {
        TileGeometry {
            tile_size: self.tile_size,
            halo: self.halo,
        }
    }

    /// The tile with id `id`.
    pub fn tile(&self, id: &str) -> Option<&TileEntry> {
        self.tiles.iter().find(|t| t.id == id)
    }

    /// The index as TOML.
    pub fn to_toml(&self) -> String {
        let body = toml::to_string(self).expect("a tile index serializes");
        format!(
            "# kfmap tile set (kfmap bake --tile-size): one .kfmap per tile, its core square\n\
             # plus the keyframes within the halo. See docs/DESIGN.md#notes-tiles.\n{body}"
        )
    }

    /// Parses and checks an index; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self, TileError> {
        let invalid = |message: String| TileError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        let index: TileIndex =
            toml::from_str(text).map_err(|e| invalid(format!("not a tile index: {e}")))?;
        if index.format != INDEX_FORMAT {
            return Err(invalid(format!(
                "tile index format {} (this build reads format {INDEX_FORMAT}): re-cut the map with this kfmap",
                index.format
            )));
        }
        index.geometry().validate().map_err(invalid)?;
        if let Some(ranking) = &index.ranking {
            ranking.validate().map_err(invalid)?;
        }
        if index.tiles.is_empty() {
            return Err(invalid("the index lists no tile".into()));
        }
        if index.tiles.len() > MAX_TILES {
            return Err(invalid(format!(
                "{} tiles listed (at most {MAX_TILES})",
                index.tiles.len()
            )));
        }
        let mut seen = std::collections::HashSet::new();
        for t in &index.tiles {
            if t.id != tile_id(t.col, t.row) {
                return Err(invalid(format!(
                    "tile {:?} has col {} row {}: its id must be {:?}",
                    t.id,
                    t.col,
                    t.row,
                    tile_id(t.col, t.row)
                )));
            }
            if !seen.insert((t.col, t.row)) {
                return Err(invalid(format!("tile {} is listed twice", t.id)));
            }
            for (what, name) in [("file", &t.file), ("pcd", &t.pcd)] {
                if !plain_file_name(name) {
                    return Err(invalid(format!(
                        "tile {}: {what} {name:?} must be a plain file name in the tile set's directory",
                        t.id
                    )));
                }
            }
            match (t.search_min, t.search_max) {
                (None, None) => {}
                (Some(low), Some(high))
                    if low.iter().chain(&high).all(|v| v.is_finite())
                        && (0..3).all(|a| low[a] <= high[a]) => {}
                _ => {
                    return Err(invalid(format!(
                        "tile {}: search-min and search-max must both be given, finite, low corner first",
                        t.id
                    )));
                }
            }
            if t.core_keyframes > t.keyframes {
                return Err(invalid(format!(
                    "tile {}: {} core keyframes of {} in all",
                    t.id, t.core_keyframes, t.keyframes
                )));
            }
        }
        Ok(index)
    }

    /// Reads `dir/tiles.toml`.
    pub fn load(dir: &Path) -> Result<Self, TileError> {
        let path = dir.join(INDEX_FILE);
        let io = |e: std::io::Error| TileError::Io {
            path: path.clone(),
            message: format!(
                "{e} (is {} a tile set from kfmap bake --tile-size?)",
                dir.display()
            ),
        };
        let len = std::fs::metadata(&path).map_err(io)?.len();
        if len > MAX_INDEX_BYTES {
            return Err(TileError::Invalid {
                path,
                message: format!("{len} bytes: larger than any tile index ({MAX_INDEX_BYTES})"),
            });
        }
        let text = std::fs::read_to_string(&path).map_err(io)?;
        Self::parse(&text, &path)
    }

    /// The tiles of `only` (ids), or all when `only` is empty; unknown ids are errors.
    pub fn select(&self, only: &[String], dir: &Path) -> Result<Vec<&TileEntry>, TileError> {
        if only.is_empty() {
            return Ok(self.tiles.iter().collect());
        }
        only.iter()
            .map(|id| {
                self.tile(id).ok_or_else(|| TileError::Unknown {
                    id: id.clone(),
                    dir: dir.to_path_buf(),
                    listed: listed(&self.tiles),
                })
            })
            .collect()
    }

    /// Autoware's `pointcloud_map_metadata.yaml`: cell size, then each tile's `.pcd`
    /// with its core square's low corner.
    pub fn autoware_metadata(&self) -> String {
        let mut yaml = format!(
            "# Written by kfmap bake --tile-size: each .pcd holds the points of its cell only.\n\
             x_resolution: {:?}\ny_resolution: {:?}\n",
            self.tile_size, self.tile_size
        );
        for t in &self.tiles {
            let [x, y] = self.geometry().core_min(t.col, t.row);
            yaml.push_str(&format!("{}: [{x:?}, {y:?}]\n", t.pcd));
        }
        yaml
    }
}

/// A few ids for an error message.
fn listed(tiles: &[TileEntry]) -> String {
    let mut ids: Vec<&str> = tiles.iter().take(8).map(|t| t.id.as_str()).collect();
    if tiles.len() > ids.len() {
        ids.push("...");
    }
    ids.join(", ")
}

/// A name with no directory part that stays in its directory.
fn plain_file_name(name: &str) -> bool {
    !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\', '\0'])
}

/// Where a request goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Route {
    /// To this tile (its position in the index).
    Tile(usize),
    /// The tile owning the guess (and every tile near enough to stand in) is down.
    Down(usize),
    /// No tile is up.
    NoneUp,
}

/// Picks the tile a request goes to from its pose guess, staying on the current tile
/// near its border (hysteresis): a client driving along a border does not flip between
/// two servers on every scan, and the halo still holds every keyframe it needs.
#[derive(Debug, Clone)]
pub struct TileRouter {
    geometry: TileGeometry,
    tiles: Vec<(i32, i32)>,
    hysteresis: f64,
    current: Option<usize>,
}

impl TileRouter {
    /// A router over `index`'s tiles; `hysteresis` (metres, at most the halo): how far
    /// past its core square a guess may go before the request changes tile.
    pub fn new(index: &TileIndex, hysteresis: f64) -> Self {
        Self {
            geometry: index.geometry(),
            tiles: index.tiles.iter().map(|t| (t.col, t.row)).collect(),
            hysteresis: hysteresis.clamp(0.0, index.halo),
            current: None,
        }
    }

    /// The default hysteresis of `index`: half its halo.
    pub fn default_hysteresis(index: &TileIndex) -> f64 {
        index.halo / 2.0
    }

    /// The tile for a guess at `(x, y)`, `up` saying which tiles answer: the current
    /// tile while the guess stays within the hysteresis of its core; else the tile whose
    /// core holds it; else (that tile down) a live tile within the hysteresis, whose halo
    /// holds what the request needs. A guess outside every core goes to the live tile
    /// whose core is nearest. Never a far tile in place of a down owner: its answer
    /// would be wrong, not merely late.
    pub fn route(&mut self, x: f64, y: f64, up: impl Fn(usize) -> bool) -> Route {
        if !(x.is_finite() && y.is_finite()) {
            return match self.current {
                Some(c) if up(c) => Route::Tile(c),
                Some(c) => Route::Down(c),
                None => Route::NoneUp,
            };
        }
        let distance = |i: usize| {
            let (col, row) = self.tiles[i];
            self.geometry.distance_to_core(col, row, x, y)
        };
        if let Some(c) = self.current.filter(|&c| up(c))
            && distance(c) <= self.hysteresis
        {
            return Route::Tile(c);
        }
        let nearest_up = (0..self.tiles.len())
            .filter(|&i| up(i))
            .min_by(|&a, &b| distance(a).total_cmp(&distance(b)));
        let owner = (0..self.tiles.len()).find(|&i| distance(i) == 0.0);
        let chosen = match (owner, nearest_up) {
            (Some(o), _) if up(o) => o,
            (Some(o), Some(n)) if distance(n) > self.hysteresis => return Route::Down(o),
            (Some(o), None) => return Route::Down(o),
            (_, Some(n)) => n,
            (None, None) => return Route::NoneUp,
        };
        self.current = Some(chosen);
        Route::Tile(chosen)
    }

    /// The tile the last request went to.
    pub fn current(&self) -> Option<usize> {
        self.current
    }
}

/// Tile `(col, row)` as a cut lists it, with made-up counts and no search region.
#[cfg(test)]
pub(crate) fn test_entry(col: i32, row: i32) -> TileEntry {
    TileEntry {
        id: tile_id(col, row),
        col,
        row,
        file: format!("{}.kfmap", tile_id(col, row)),
        pcd: format!("{}.pcd", tile_id(col, row)),
        keyframes: 0,
        core_keyframes: 0,
        points: 0,
        bytes: 0,
        search_min: None,
        search_max: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn index(tiles: &[(i32, i32)], size: f64, halo: f64) -> TileIndex {
        TileIndex {
            format: INDEX_FORMAT,
            tile_size: size,
            halo,
            keyframes: 0,
            tiles: tiles
                .iter()
                .map(|&(col, row)| test_entry(col, row))
                .collect(),
            ranking: None,
        }
    }

    #[test]
    fn a_point_belongs_to_its_core_tile_and_the_halos_that_reach_it() {
        let g = TileGeometry {
            tile_size: 10.0,
            halo: 2.0,
        };
        // Brute force over a window of tiles: in the halo box iff within 2 m (Chebyshev).
        let mut rng = 12345_u64;
        for _ in 0..2000 {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let x = ((rng >> 11) as f64 / (1u64 << 53) as f64) * 60.0 - 30.0;
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let y = ((rng >> 11) as f64 / (1u64 << 53) as f64) * 60.0 - 30.0;
            let held = g.tiles_holding(x, y);
            assert_eq!(
                held[0],
                ((x / 10.0).floor() as i32, (y / 10.0).floor() as i32)
            );
            let mut expected = Vec::new();
            for row in -5..5 {
                for col in -5..5 {
                    let (x0, y0) = (col as f64 * 10.0, row as f64 * 10.0);
                    let inside = x >= x0 - 2.0 && x <= x0 + 12.0 && y >= y0 - 2.0 && y <= y0 + 12.0;
                    if inside {
                        expected.push((col, row));
                    }
                }
            }
            let mut got = held.clone();
            got.sort();
            expected.sort();
            assert_eq!(got, expected, "({x}, {y})");
        }
    }

    #[test]
    fn the_router_keeps_its_tile_within_the_hysteresis_and_changes_past_it() {
        let idx = index(&[(0, 0), (1, 0)], 10.0, 4.0);
        let mut router = TileRouter::new(&idx, 2.0);
        let all = |_: usize| true;
        assert_eq!(router.route(9.0, 5.0, all), Route::Tile(0));
        // Past the border by less than the hysteresis: stays.
        assert_eq!(router.route(11.5, 5.0, all), Route::Tile(0));
        // Past it by more: hands over, and then stays on the new tile back to 8.5.
        assert_eq!(router.route(12.5, 5.0, all), Route::Tile(1));
        assert_eq!(router.route(8.5, 5.0, all), Route::Tile(1));
        assert_eq!(router.route(7.5, 5.0, all), Route::Tile(0));
        // The owner down: a neighbour within the hysteresis stands in, a far one never.
        assert_eq!(router.route(11.0, 5.0, |i| i == 0), Route::Tile(0));
        assert_eq!(router.route(15.0, 5.0, |i| i == 0), Route::Down(1));
        assert_eq!(router.route(15.0, 5.0, |_| false), Route::Down(1));
        // Outside every core: the nearest live tile, or none.
        let mut fresh = TileRouter::new(&idx, 2.0);
        assert_eq!(fresh.route(40.0, -3.0, all), Route::Tile(1));
        assert_eq!(fresh.route(40.0, -3.0, |_| false), Route::NoneUp);
    }

    #[test]
    fn an_index_round_trips_and_bad_ones_are_named() {
        let idx = index(&[(0, 0), (-1, 2)], 250.0, 50.0);
        let path = Path::new("tiles.toml");
        assert_eq!(TileIndex::parse(&idx.to_toml(), path).unwrap(), idx);
        let yaml = idx.autoware_metadata();
        assert!(yaml.contains("x_resolution: 250.0"), "{yaml}");
        assert!(yaml.contains("x-1_y2.pcd: [-250.0, 500.0]"), "{yaml}");
        let mut bad = idx.clone();
        bad.tiles[1].id = "x5_y5".into();
        let e = TileIndex::parse(&bad.to_toml(), path).unwrap_err();
        assert!(e.to_string().contains("its id must be \"x-1_y2\""), "{e}");
        let mut bad = idx.clone();
        bad.tiles[0].file = "../../etc/passwd".into();
        let e = TileIndex::parse(&bad.to_toml(), path).unwrap_err();
        assert!(e.to_string().contains("plain file name"), "{e}");
        let mut bad = idx.clone();
        bad.tiles.push(bad.tiles[0].clone());
        let e = TileIndex::parse(&bad.to_toml(), path).unwrap_err();
        assert!(e.to_string().contains("listed twice"), "{e}");
        let mut bad = idx.clone();
        bad.tile_size = f64::NAN;
        let e = TileIndex::parse(&bad.to_toml(), path).unwrap_err();
        assert!(e.to_string().contains("tile-size"), "{e}");
        let e = TileIndex::parse("format = 1\n[[tile]]\nid = 3\n", path).unwrap_err();
        assert!(e.to_string().contains("not a tile index"), "{e}");
        let e = idx
            .select(&["x9_y9".into()], Path::new("/site"))
            .unwrap_err();
        assert!(e.to_string().contains("x0_y0, x-1_y2"), "{e}");
        // A published ranking round-trips; one the servers would refuse is refused
        // here too, naming the option (the server's own check).
        let ranked = TileIndex {
            ranking: Some(PlaceRanking {
                ambiguity_margin: 0.2,
                ..PlaceRanking::default()
            }),
            ..idx.clone()
        };
        assert_eq!(TileIndex::parse(&ranked.to_toml(), path).unwrap(), ranked);
        for (bad, option) in [
            (
                PlaceRanking {
                    distinct_m: 0.0,
                    ..PlaceRanking::default()
                },
                "distinct-m",
            ),
            (
                PlaceRanking {
                    keep_ratio: 1.5,
                    ..PlaceRanking::default()
                },
                "keep-ratio",
            ),
            (
                PlaceRanking {
                    separation_deg: f64::NAN,
                    ..PlaceRanking::default()
                },
                "separation-deg",
            ),
        ] {
            let text = TileIndex {
                ranking: Some(bad),
                ..idx.clone()
            }
            .to_toml();
            let e = TileIndex::parse(&text, path).unwrap_err();
            assert!(e.to_string().contains(option), "{e}");
        }
    }
}
