//! Branch-and-bound search of a levelled scan over the place grid: every yaw on a step
//! fine enough that the farthest point moves less than a voxel, every translation of a
//! region on the voxel lattice. A node is a yaw and a cube of `2^l` translations per
//! axis; its bound is the number of scan points that land on marked level-`l` voxels,
//! at least the hits of any translation inside it. Nodes are expanded best bound first,
//! so leaves (single translations, whose bound is their exact hit count) come out in
//! falling order of hits and the first is the best placement on the lattice.

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::f64::consts::TAU;
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::grid::{GridView, SearchRegion, every_voxel};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::options::{InvalidOption, ensure, ensure_ratio};

/// Nodes expanded together (their children bounded in parallel): enough to keep
/// every thread busy, few enough that little is expanded a best-first order would not.
const EXPAND_BATCH: usize = 128;

/// How the search runs (`server.toml [relocalize.search]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct SearchParams {
    /// Distinct placements to return at most.
    pub candidates: usize,
    /// Placements hitting fewer than this fraction of the points are not returned.
    pub min_hit_ratio: f64,
    /// Placements hitting fewer than this fraction of the best one's hits are not
    /// returned (they would not survive verification).
    pub keep_ratio: f64,
    /// Two placements closer than this (metres) and `separation_deg` are one place.
    pub separation_m: f64,
    /// See `separation_m`, degrees.
    pub separation_deg: f64,
    /// Most point lookups before the search stops with what it has (bounds the work
    /// of a scan that fits nowhere or everywhere).
    pub max_lookups: u64,
    /// Yaws are tried on a step that moves a point this far away (metres, or the
    /// farthest point when nearer) by one voxel; farther points move more.
    pub yaw_range: f64,
}

impl SearchParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure(
            (1..=64).contains(&self.candidates),
            "candidates",
            self.candidates,
            "1 to 64",
        )?;
        ensure_ratio("min-hit-ratio", self.min_hit_ratio)?;
        ensure_ratio("keep-ratio", self.keep_ratio)?;
        ensure(
            positive(self.separation_m),
            "separation-m",
            self.separation_m,
            "> 0 m",
        )?;
        ensure(
            positive(self.separation_deg),
            "separation-deg",
            self.separation_deg,
            "> 0 degrees",
        )?;
        ensure(
            self.max_lookups >= 1_000_000,
            "max-lookups",
            self.max_lookups,
            "at least 1000000",
        )?;
        ensure(
            positive(self.yaw_range) && self.yaw_range <= 1000.0,
            "yaw-range",
            self.yaw_range,
            "a range > 0 and <= 1000 m",
        )
    }
}

impl Default for SearchParams {
    fn default() -> Self {
        Self {
            candidates: 6,
            min_hit_ratio: 0.3,
            keep_ratio: 0.7,
            separation_m: 2.0,
            separation_deg: 20.0,
            max_lookups: 400_000_000,
            yaw_range: 30.0,
        }
    }
}

/// One placement of the scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// `T_grid_levelled`: the yaw about z (then `grid_from_levelled`) and translation.
    pub pose: Pose,
    /// Yaw, radians in [0, 2 pi).
    pub yaw: f64,
    /// Scan points landing on marked voxels.
    pub hits: u32,
    /// `hits` over the points searched.
    pub hit_ratio: f64,
}

/// What a search found and what it cost.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SearchOutcome {
    /// Distinct placements, most hits first.
    pub placements: Vec<Placement>,
    /// Points placed.
    pub points: usize,
    /// Yaws tried.
    pub yaws: usize,
    /// Nodes whose bound was computed.
    pub nodes: u64,
    /// True when `max-lookups` stopped the search before it was complete.
    pub exhausted: bool,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    bound: u32,
    level: u8,
    yaw: u16,
    k: [i32; 3],
    /// Where the node's hits (the points it counted as marked) start in the search's
    /// [`HitMasks`]: its children look up only those.
    hits: usize,
}

impl PartialEq for Node {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Node {}

impl Ord for Node {
    /// Higher bound first; on a tie the deeper node, which reaches a leaf sooner; then
    /// the lower yaw and lattice translation (z, y, x), not the heap's history, so that
    /// equal-hit placements present together are taken in the same order on every grid
    /// of a map (a tile's and the whole map's: equal hits at z 0 and 1 m, the lower).
    /// Coarser-first on a tie would settle every tie but expanded open ground's many
    /// equal bounds to the work limit (the corridor test's scan 0 placed 112 m off).
    fn cmp(&self, other: &Self) -> Ordering {
        let key = |n: &Self| (n.yaw, n.k[2], n.k[1], n.k[0]);
        self.bound
            .cmp(&other.bound)
            .then_with(|| other.level.cmp(&self.level))
            .then_with(|| key(other).cmp(&key(self)))
    }
}

impl PartialOrd for Node {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The yaw step that moves a point at `range` metres by at most `resolution`.
pub fn yaw_step(resolution: f64, range: f64) -> f64 {
    (resolution / range.max(resolution)).clamp(0.2_f64.to_radians(), 10.0_f64.to_radians())
}

/// Which columns (grid-frame x, y) of a region's lattice a search places the scan at.
#[derive(Clone, Copy)]
pub enum Columns<'a> {
    /// Every column.
    All,
    /// Those the table marks: a tile's share of a search over a tile set
    /// (`crate::tiles::SearchShare`), so that every translation is tried by one tile.
    Owned(&'a OwnedColumns),
}

/// The best hit ratio that other searches of the same scan have reached so far: the
/// tiles one process serves, each searching its share at once. The client ranking
/// every tile's places keeps none below `keep-ratio` of the best of them all, so a
/// search need not look for one below `keep-ratio` of a peer's best either: the places
/// it still returns are those it would have returned, in the same order, and only
/// places no client keeps go unsearched.
#[derive(Debug, Default)]
pub struct PeerBest(AtomicU64);

impl PeerBest {
    /// The best hit ratio offered so far (0 before any).
    pub fn ratio(&self) -> f64 {
        f64::from_bits(self.0.load(AtomicOrdering::Relaxed))
    }

    /// Offers a placement's hit ratio (non-negative floats order as their bits do).
    pub fn offer(&self, hit_ratio: f64) {
        if hit_ratio.is_finite() && hit_ratio > 0.0 {
            self.0
                .fetch_max(hit_ratio.to_bits(), AtomicOrdering::Relaxed);
        }
    }
}

/// Places `points` (levelled sensor frame: z up, yaw unknown) over `grid` at every yaw
/// and every lattice translation inside `region` in `columns`, best bound first (see
/// `Lattice::branch_and_bound`). `grid_from_levelled` turns the yawed points into the
/// grid's frame: identity when the scan was levelled on its floors as the grid was,
/// the grid's `grid_from_map` when it was levelled on the map's z (an IMU's gravity).
/// With `peers`, the search offers its best to them and keeps above their best (see
/// [`PeerBest`]).
pub fn search(
    grid: &GridView<'_>,
    points: &[[f64; 3]],
    region: &SearchRegion,
    columns: Columns<'_>,
    peers: Option<&PeerBest>,
    params: &SearchParams,
    grid_from_levelled: &UnitQuaternion<f64>,
) -> SearchOutcome {
    let n = points.len();
    let range = points
        .iter()
        .map(|p| p[0].hypot(p[1]))
        .fold(0.0_f64, f64::max)
        .min(params.yaw_range);
    let yaws = (TAU / yaw_step(grid.resolution(), range)).ceil() as usize;
    let searched = if n == 0 || !region.min.iter().zip(&region.max).all(|(a, b)| a <= b) {
        SearchOutcome::default()
    } else {
        // On one of the pool's threads: each of the search's hundreds of batches is a
        // parallel step, which a thread outside the pool would hand over and wait for.
        rayon::scope(|_| {
            Lattice::new(grid, points, region, columns, yaws, grid_from_levelled)
                .branch_and_bound(params, peers)
        })
    };
    SearchOutcome {
        points: n,
        yaws,
        ..searched
    }
}

/// True when `placement` is within the separation of one of `kept`.
fn same_place(kept: &[Placement], placement: &Placement, params: &SearchParams) -> bool {
    let separation_rad = params.separation_deg.to_radians();
    kept.iter().any(|p| {
        (p.pose.translation.vector - placement.pose.translation.vector).norm() < params.separation_m
            && angle_between(p.yaw, placement.yaw) < separation_rad
    })
}

/// The scan's points on the grid's voxel lattice at every yaw.
struct Lattice<'g, 'c> {
    grid: &'g GridView<'g>,
    region: SearchRegion,
    yaws: usize,
    /// Translations per axis: `region.min + k r`, `k` in `[0, spans)`.
    spans: [i32; 3],
    /// The columns searched; `None`: all.
    owned: Option<&'c OwnedColumns>,
    /// The top level searched.
    top: usize,
    /// Applied after each yaw: see [`search`].
    grid_from_levelled: UnitQuaternion<f64>,
    /// Voxel of each point at each yaw with the region's low corner as translation;
    /// translation `min + k r` moves every point by exactly `k` voxels.
    voxels: Vec<Vec<[i64; 3]>>,
}

impl<'g, 'c> Lattice<'g, 'c> {
    fn new(
        grid: &'g GridView<'g>,
        points: &[[f64; 3]],
        region: &SearchRegion,
        columns: Columns<'c>,
        yaws: usize,
        grid_from_levelled: &UnitQuaternion<f64>,
    ) -> Self {
        let r = grid.resolution();
        let spans = lattice_spans(region, r);
        let owned = match columns {
            Columns::All => None,
            Columns::Owned(table) => {
                // A table of another lattice would search the wrong columns.
                assert!(
                    table.region == *region && table.resolution == r,
                    "a column table of another search region"
                );
                Some(table)
            }
        };
        let origin = grid.origin();
        let voxels = (0..yaws)
            .into_par_iter()
            .map(|y| {
                let rotation = grid_from_levelled * yaw_rotation(y as f64 * TAU / yaws as f64);
                points
                    .iter()
                    .map(|p| {
                        let v = rotation * Vector3::from(*p);
                        [0, 1, 2].map(|a| ((v[a] + region.min[a] - origin[a]) / r).floor() as i64)
                    })
                    .collect()
            })
            .collect();
        let widest = *spans.iter().max().expect("three axes");
        let top = (0..grid.levels())
            .find(|&l| (1_i64 << l) >= i64::from(widest))
            .unwrap_or(grid.levels() - 1);
        Self {
            grid,
            region: *region,
            yaws,
            spans,
            owned,
            top,
            grid_from_levelled: *grid_from_levelled,
            voxels,
        }
    }

    /// True when the cube of `side` translations per axis from `k` holds a column
    /// searched.
    fn searched(&self, k: [i32; 3], side: i32) -> bool {
        self.owned.is_none_or(|o| o.any(k, side))
    }

    /// Points of yaw `yaw` landing on marked level-`level` voxels at translation `k`,
    /// of those set in `among` (its parent's hits), written to `hits`; less than `need`
    /// when it cannot reach it (`GridView::count_marked_among`).
    fn bound(&self, (level, yaw, k): Cube, among: &[u64], need: u32, hits: &mut [u64]) -> u32 {
        self.grid.count_marked_among(
            level,
            &self.voxels[yaw as usize],
            k.map(i64::from),
            among,
            need,
            hits,
        )
    }

    /// Best-first branch and bound over every yaw. Nodes are expanded in batches of
    /// the best `EXPAND_BATCH` (their children bounded in parallel); a leaf is taken
    /// only when it is the best node left, so leaves still come out best first.
    fn branch_and_bound(&self, params: &SearchParams, peers: Option<&PeerBest>) -> SearchOutcome {
        let n = self.voxels.first().map_or(0, Vec::len);
        let r = self.grid.resolution();
        let mut outcome = SearchOutcome::default();
        let floor_hits = (params.min_hit_ratio * n as f64).ceil() as u32;
        let side = 1_usize << self.top;
        let mut masks = HitMasks::new(n);
        let mut tops = Vec::new();
        for yaw in 0..self.yaws {
            for kz in (0..self.spans[2]).step_by(side) {
                for ky in (0..self.spans[1]).step_by(side) {
                    for kx in (0..self.spans[0]).step_by(side) {
                        if self.searched([kx, ky, kz], side as i32) {
                            tops.push(((self.top, yaw as u16, [kx, ky, kz]), HitMasks::ALL));
                        }
                    }
                }
            }
        }
        let mut heap = BinaryHeap::new();
        let mut lookups: u64 = 0;
        self.bound_all(&tops, floor_hits, &mut heap, &mut masks);
        outcome.nodes += tops.len() as u64;
        lookups += (tops.len() * n) as u64;
        let mut batch = Vec::with_capacity(EXPAND_BATCH);
        let mut children = Vec::with_capacity(EXPAND_BATCH * 8);
        // A peer's ratio as hits of this scan's points; the slack keeps its rounding
        // from pruning a place the client would keep.
        let peer_hits = || {
            peers.map_or(0, |p| {
                (params.keep_ratio * p.ratio() * n as f64 - 1e-6)
                    .ceil()
                    .max(0.0) as u32
            })
        };
        loop {
            let best = outcome.placements.first().map_or(0, |p| p.hits);
            let threshold = floor_hits
                .max((params.keep_ratio * f64::from(best)).ceil() as u32)
                .max(peer_hits());
            match heap.peek() {
                None => break,
                Some(node) if node.bound < threshold => break,
                Some(_) if outcome.placements.len() >= params.candidates => break,
                Some(_) if lookups > params.max_lookups => {
                    outcome.exhausted = true;
                    break;
                }
                Some(node) if node.level == 0 => {
                    let node = heap.pop().expect("peeked");
                    let yaw = node.yaw as f64 * TAU / self.yaws as f64;
                    let t = [0, 1, 2].map(|a| self.region.min[a] + f64::from(node.k[a]) * r);
                    let placement = Placement {
                        pose: Isometry3::from_parts(
                            Translation3::new(t[0], t[1], t[2]),
                            self.grid_from_levelled * yaw_rotation(yaw),
                        ),
                        yaw,
                        hits: node.bound,
                        hit_ratio: f64::from(node.bound) / n as f64,
                    };
                    if !same_place(&outcome.placements, &placement, params) {
                        if let Some(peers) = peers {
                            peers.offer(placement.hit_ratio);
                        }
                        outcome.placements.push(placement);
                    }
                    continue;
                }
                Some(_) => {}
            }
            batch.clear();
            while batch.len() < EXPAND_BATCH
                && heap
                    .peek()
                    .is_some_and(|node| node.level > 0 && node.bound >= threshold)
            {
                batch.push(heap.pop().expect("peeked"));
            }
            children.clear();
            for node in &batch {
                let level = node.level as usize - 1;
                let half = 1_i32 << level;
                for dz in [0, half] {
                    for dy in [0, half] {
                        for dx in [0, half] {
                            let k = [node.k[0] + dx, node.k[1] + dy, node.k[2] + dz];
                            if (0..3).all(|a| k[a] < self.spans[a]) && self.searched(k, half) {
                                children.push(((level, node.yaw, k), node.hits));
                            }
                        }
                    }
                }
            }
            self.bound_all(&children, threshold, &mut heap, &mut masks);
            outcome.nodes += children.len() as u64;
            lookups += (children.len() * n) as u64;
        }
        outcome
    }

    /// Bounds `nodes` (each with where its parent's hits are) in parallel and keeps
    /// those reaching `threshold`, their hits added to `masks`.
    fn bound_all(
        &self,
        nodes: &[(Cube, usize)],
        threshold: u32,
        heap: &mut BinaryHeap<Node>,
        masks: &mut HitMasks,
    ) {
        let words = masks.words;
        let mut hits = vec![0_u64; nodes.len() * words];
        let bounds: Vec<u32> = nodes
            .par_iter()
            .zip(hits.par_chunks_mut(words))
            .with_min_len(16)
            .map(|(&(node, parent), hits)| self.bound(node, masks.of(parent), threshold, hits))
            .collect();
        for ((&((level, yaw, k), _), bound), hits) in
            nodes.iter().zip(bounds).zip(hits.chunks(words))
        {
            if bound >= threshold {
                heap.push(Node {
                    bound,
                    level: level as u8,
                    yaw,
                    k,
                    hits: masks.push(hits),
                });
            }
        }
    }
}

/// A node's level, yaw and lattice translation.
type Cube = (usize, u16, [i32; 3]);

/// The hits of every node a search keeps, one bit per point, back to back: a node's
/// children look up only the points their parent found marked (the rest cannot be).
struct HitMasks {
    /// Words per node.
    words: usize,
    /// [`Self::ALL`]'s mask (every point), then each kept node's.
    bits: Vec<u64>,
}

impl HitMasks {
    /// Where the mask of every point is: the top nodes' parent.
    const ALL: usize = 0;

    fn new(points: usize) -> Self {
        let bits = every_voxel(points);
        Self {
            words: bits.len(),
            bits,
        }
    }

    fn of(&self, at: usize) -> &[u64] {
        &self.bits[at..at + self.words]
    }

    /// Adds a node's hits; returns where they are.
    fn push(&mut self, hits: &[u64]) -> usize {
        let at = self.bits.len();
        self.bits.extend_from_slice(hits);
        at
    }
}

/// Translations per axis of `region`'s lattice: `region.min + k r`, `k` in `[0, spans)`.
fn lattice_spans(region: &SearchRegion, resolution: f64) -> [i32; 3] {
    [0, 1, 2].map(|a| ((region.max[a] - region.min[a]) / resolution).floor() as i32 + 1)
}

/// The columns of a region's lattice a search may use, as a summed-area table: whether
/// a node's square of columns holds one is a constant-time look. Built once per served
/// tile (about 3 ms for a 250 m tile's 75 000 columns), not per search.
#[derive(Debug, Clone, PartialEq)]
pub struct OwnedColumns {
    /// The lattice it was built for.
    region: SearchRegion,
    resolution: f64,
    /// Columns per axis (x, y).
    spans: [i32; 2],
    /// `sums[y * (spans[0] + 1) + x]`: owned columns with both indices below `(x, y)`.
    sums: Vec<u32>,
}

impl OwnedColumns {
    /// The columns `(x, y)` of `region`'s lattice (steps of `resolution`) that `owns`.
    pub fn new(region: &SearchRegion, resolution: f64, owns: impl Fn(f64, f64) -> bool) -> Self {
        let [sx, sy, _] = lattice_spans(region, resolution);
        let spans = [sx.max(0), sy.max(0)];
        let width = spans[0] as usize + 1;
        let mut sums = vec![0_u32; width * (spans[1] as usize + 1)];
        for ky in 0..spans[1] as usize {
            let y = region.min[1] + ky as f64 * resolution;
            let mut row = 0;
            for kx in 0..spans[0] as usize {
                row += u32::from(owns(region.min[0] + kx as f64 * resolution, y));
                sums[(ky + 1) * width + kx + 1] = sums[ky * width + kx + 1] + row;
            }
        }
        Self {
            region: *region,
            resolution,
            spans,
            sums,
        }
    }

    /// True when a column of the square of `side` from `k` (clipped to the lattice)
    /// is owned.
    fn any(&self, k: [i32; 3], side: i32) -> bool {
        let width = self.spans[0] as usize + 1;
        let [x0, y0] = [k[0].max(0), k[1].max(0)].map(|v| v as usize);
        let x1 = (k[0] + side).min(self.spans[0]).max(0) as usize;
        let y1 = (k[1] + side).min(self.spans[1]).max(0) as usize;
        if x1 <= x0 || y1 <= y0 {
            return false;
        }
        let at = |x: usize, y: usize| self.sums[y * width + x];
        at(x1, y1) + at(x0, y0) > at(x0, y1) + at(x1, y0)
    }
}

fn yaw_rotation(yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
}

/// Absolute difference of two angles, radians in [0, pi].
fn angle_between(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(TAU);
    d.min(TAU - d)
}
