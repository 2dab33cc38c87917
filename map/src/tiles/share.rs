//! Each tile's share of relocalization over a tile set: the translations its search
//! tries in the places phase. The shares partition the translations the tiles' search
//! regions hold, so a search over every tile tries each translation once, as one search
//! over the merged map does (docs/DESIGN.md#notes-tiles).

use super::{TileGeometry, TileIndex};

/// A translation's owner among the tiles whose search region holds its column: the tile
/// whose core square holds it, else the tile whose core square is nearest (a column in
/// a square no tile holds), ties to the lowest (row, col). Columns are the place grid's
/// (its levelled frame): every tile of a set shares that frame and lattice.
#[derive(Debug, Clone, PartialEq)]
pub struct SearchShare {
    geometry: TileGeometry,
    own: (i32, i32),
    /// Tiles whose search region meets this tile's (itself included): (col, row, low
    /// corner x y, high corner x y).
    rivals: Vec<(i32, i32, [f64; 2], [f64; 2])>,
}

impl SearchShare {
    /// Tile `id`'s share; `None` when the index gives it no search region (a cut by an
    /// older kfmap, or a tile without a place grid): it then searches its whole region.
    pub fn of(index: &TileIndex, id: &str) -> Option<Self> {
        let own = index.tile(id)?;
        let (low, high) = (own.search_min?, own.search_max?);
        let meets = |l: [f64; 3], h: [f64; 3]| (0..2).all(|a| l[a] <= high[a] && h[a] >= low[a]);
        let rivals = index
            .tiles
            .iter()
            .filter_map(|t| Some((t, t.search_min?, t.search_max?)))
            .filter(|&(_, l, h)| meets(l, h))
            .map(|(t, l, h)| (t.col, t.row, [l[0], l[1]], [h[0], h[1]]))
            .collect();
        Some(Self {
            geometry: index.geometry(),
            own: (own.col, own.row),
            rivals,
        })
    }

    /// True when this tile searches translations at column `(x, y)`.
    pub fn owns(&self, x: f64, y: f64) -> bool {
        let holds = |l: &[f64; 2], h: &[f64; 2]| x >= l[0] && x <= h[0] && y >= l[1] && y <= h[1];
        let core = self.geometry.tile_of(x, y);
        let owner = self
            .rivals
            .iter()
            .filter(|(_, _, l, h)| holds(l, h))
            .map(|&(col, row, _, _)| {
                // Below any other: a column on a shared edge is its core tile's.
                let distance = if (col, row) == core {
                    -1.0
                } else {
                    self.geometry.distance_to_core(col, row, x, y)
                };
                (distance, row, col)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
        owner.is_some_and(|(_, row, col)| (col, row) == self.own)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tiles::{INDEX_FORMAT, TileEntry, test_entry};
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// Tiles of 10 m on a ring with holes (squares no tile holds), each with a search
    /// region of its own extent around its core, as a cut writes them.
    fn ring_index(rng: &mut StdRng) -> TileIndex {
        let mut tiles = Vec::new();
        for row in -2..3 {
            for col in -2..3 {
                if (row, col) == (0, 0) || rng.random_bool(0.2) {
                    continue;
                }
                let (x0, y0) = (f64::from(col) * 10.0, f64::from(row) * 10.0);
                let mut grow = || rng.random_range(-2.0..14.0);
                let low = [x0 - grow(), y0 - grow(), -1.0];
                let high = [x0 + 10.0 + grow(), y0 + 10.0 + grow(), 3.0];
                tiles.push(TileEntry {
                    search_min: Some(low),
                    search_max: Some(high),
                    ..test_entry(col, row)
                });
            }
        }
        TileIndex {
            format: INDEX_FORMAT,
            tile_size: 10.0,
            halo: 10.0,
            keyframes: 0,
            tiles,
            ranking: None,
        }
    }

    /// Every column some tile's region holds is owned by exactly one tile (each tile
    /// deciding alone), one whose region holds it and whose core is nearest of those:
    /// the column's own core tile when its region holds it. A column no region holds is
    /// no tile's. Brute force over every tile, on the lattice and between its points.
    #[test]
    fn the_tiles_shares_split_every_searched_column_once() {
        let mut rng = StdRng::seed_from_u64(35);
        for _ in 0..5 {
            let index = ring_index(&mut rng);
            let shares: Vec<SearchShare> = index
                .tiles
                .iter()
                .map(|t| SearchShare::of(&index, &t.id).expect("a region"))
                .collect();
            let geometry = index.geometry();
            for i in 0..4000 {
                let (x, y) = if i % 2 == 0 {
                    (
                        f64::from(rng.random_range(-45..46)),
                        f64::from(rng.random_range(-45..46)),
                    )
                } else {
                    (rng.random_range(-45.0..45.0), rng.random_range(-45.0..45.0))
                };
                let holding: Vec<&TileEntry> = index
                    .tiles
                    .iter()
                    .filter(|t| {
                        let (l, h) = (t.search_min.unwrap(), t.search_max.unwrap());
                        x >= l[0] && x <= h[0] && y >= l[1] && y <= h[1]
                    })
                    .collect();
                let owners: Vec<usize> = (0..shares.len())
                    .filter(|&s| shares[s].owns(x, y))
                    .collect();
                if holding.is_empty() {
                    assert!(owners.is_empty(), "({x}, {y}) is in no region but owned");
                    continue;
                }
                assert_eq!(owners.len(), 1, "({x}, {y}) owned by {owners:?}");
                let owner = &index.tiles[owners[0]];
                assert!(holding.iter().any(|t| t.id == owner.id));
                let core = geometry.tile_of(x, y);
                if holding.iter().any(|t| (t.col, t.row) == core) {
                    assert_eq!((owner.col, owner.row), core, "({x}, {y})");
                } else {
                    let nearest = holding
                        .iter()
                        .map(|t| geometry.distance_to_core(t.col, t.row, x, y))
                        .fold(f64::INFINITY, f64::min);
                    let d = geometry.distance_to_core(owner.col, owner.row, x, y);
                    assert_eq!(d, nearest, "({x}, {y})");
                }
            }
        }
    }

    /// A cut without search regions (an older kfmap) gives no share.
    #[test]
    fn an_index_without_regions_gives_no_share() {
        let mut rng = StdRng::seed_from_u64(1);
        let mut index = ring_index(&mut rng);
        for t in &mut index.tiles {
            t.search_min = None;
            t.search_max = None;
        }
        let id = index.tiles[0].id.clone();
        assert_eq!(SearchShare::of(&index, &id), None);
    }
}
