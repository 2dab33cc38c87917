//! Relocalization of one scan with no pose guess: level it, propose placements by the
//! branch-and-bound search over the map's place grid, verify each by coarse-to-fine
//! registration against the map, and answer `found`, `ambiguous` or `not-found`.

use std::collections::HashMap;
use std::f64::consts::{PI, TAU};

use nalgebra::{UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::grid::GridView;
use super::level::{estimate_up, levelling};
use super::search::{Columns, PeerBest, SearchOutcome, SearchParams, search};
use crate::map::NearestMemo;
use crate::select::SelectionOptions;
use kfmap_geometry::cloud::{CloudError, PointCloud};
use kfmap_geometry::geometry::{PackedSym3, Pose, rotation_distance, translation_distance};
use kfmap_geometry::options::{InvalidOption, ensure, ensure_ratio};
use kfmap_geometry::registration::RegistrationResult;
use kfmap_geometry::tracking::{Stage, TrackingParams, pose_covariance};

/// How relocalization runs (`server.toml [relocalize]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct RelocalizeParams {
    /// Scan points farther than this (horizontally) are not searched with, metres,
    /// unless fewer than `MIN_STRUCTURE_POINTS` off the ground lie within it (open
    /// ground): the range then doubles, twice at most.
    pub max_range: f64,
    /// Nor nearer than this (the operator, the robot itself), metres.
    pub min_range: f64,
    /// The scan is thinned to about this many points for the search.
    pub search_points: usize,
    /// The sensor tilts less than this from the vertical (levelling gate), degrees.
    pub max_tilt_deg: f64,
    /// Each proposed place is settled (coarse iterations from where the search put it)
    /// on the coarse scan thinned to at most this many points ([`thinned_scan`]); 0: on
    /// every coarse point. Settling is most of the scoring phase's work; thinned, the
    /// runner-up places settle otherwise (docs/DESIGN.md#notes-relocalization).
    pub settle_points: usize,
    /// ... and scored (fine pairing distance) on the coarse scan thinned to at most this
    /// many points; 0: on every coarse point.
    pub score_points: usize,
    /// The best place's final registration (and its tight fit) runs on the scan as
    /// sent thinned to at most this many points; 0: on every point. A tracker
    /// refines the pose on its next scan; the verdict needs shares, not millimetres.
    pub final_points: usize,
    /// The place search.
    pub search: SearchParams,
    /// `found` needs this share of the scan paired at the request's distance...
    pub found_inlier_ratio: f64,
    /// ... and this share within `tight-distance` times it.
    pub found_tight_ratio: f64,
    /// See `found-tight-ratio`.
    pub tight_distance: f64,
    /// A runner-up scoring within this of the best makes the answer `ambiguous`.
    pub ambiguity_margin: f64,
    /// A runner-up is another place when farther than this from the best, metres...
    pub distinct_m: f64,
    /// ... or turned more than this, degrees.
    pub distinct_deg: f64,
    /// An `ambiguous` verdict is `found` when the best place pins the scan (a 0.5 m
    /// slide along its least constrained horizontal direction loses at least this
    /// share of the structure it explains, [`super::pinning`]) and every other place
    /// within the margin, registered as the best was, slides (loses less) and explains
    /// at least `explained-lead` less, give or take the share's sampling noise: a
    /// place along a corridor-like stretch is no rival to one the scan pins. 0: never.
    pub pinned_share: f64,
    /// See `pinned-share` (share of the scan's structure). 0 by default: the rival
    /// may explain no more than the best beyond two standard errors of the best's
    /// share ([`Pinning::share_noise`]); a fixed lead of 0.015, and later none, lay
    /// within that noise and turned verdicts on millimetres of the best place's pose.
    pub explained_lead: f64,
}

impl RelocalizeParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure(
            positive(self.max_range) && self.max_range <= 1000.0,
            "max-range",
            self.max_range,
            "a range > 0 and <= 1000 m",
        )?;
        ensure(
            self.min_range.is_finite() && self.min_range >= 0.0 && self.min_range < self.max_range,
            "min-range",
            self.min_range,
            "0 m up to max-range",
        )?;
        ensure(
            (10..=100_000).contains(&self.search_points),
            "search-points",
            self.search_points,
            "10 to 100000",
        )?;
        for (key, points) in [
            ("settle-points", self.settle_points),
            ("score-points", self.score_points),
        ] {
            ensure(
                points == 0 || (100..=100_000).contains(&points),
                key,
                points,
                "0 (every coarse point) or 100 to 100000",
            )?;
        }
        ensure(
            self.final_points == 0 || (1000..=1_000_000).contains(&self.final_points),
            "final-points",
            self.final_points,
            "0 (every point) or 1000 to 1000000",
        )?;
        ensure(
            self.max_tilt_deg.is_finite() && (1.0..=90.0).contains(&self.max_tilt_deg),
            "max-tilt-deg",
            self.max_tilt_deg,
            "1 to 90 degrees",
        )?;
        ensure_ratio("found-inlier-ratio", self.found_inlier_ratio)?;
        ensure_ratio("found-tight-ratio", self.found_tight_ratio)?;
        ensure(
            positive(self.tight_distance) && self.tight_distance <= 1.0,
            "tight-distance",
            self.tight_distance,
            "a fraction > 0 and <= 1 of the pairing distance",
        )?;
        ensure_ratio("ambiguity-margin", self.ambiguity_margin)?;
        ensure(
            positive(self.distinct_m),
            "distinct-m",
            self.distinct_m,
            "> 0 m",
        )?;
        ensure(
            positive(self.distinct_deg),
            "distinct-deg",
            self.distinct_deg,
            "> 0 degrees",
        )?;
        ensure_ratio("pinned-share", self.pinned_share)?;
        ensure_ratio("explained-lead", self.explained_lead)?;
        self.search.validate()
    }
}

impl Default for RelocalizeParams {
    fn default() -> Self {
        Self {
            max_range: 30.0,
            min_range: 0.5,
            search_points: 300,
            max_tilt_deg: 40.0,
            settle_points: 1100,
            score_points: 0,
            final_points: 10_000,
            search: SearchParams {
                candidates: 5,
                ..SearchParams::default()
            },
            found_inlier_ratio: 0.5,
            found_tight_ratio: 0.4,
            tight_distance: 0.3,
            ambiguity_margin: 0.05,
            distinct_m: 1.0,
            distinct_deg: 5.0,
            pinned_share: 0.05,
            explained_lead: 0.0,
        }
    }
}

/// The verdict of a relocalization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum RelocalizeStatus {
    /// One place fits, clearly better than any other.
    Found = 0,
    /// Two places fit almost equally (symmetric corridors); the pose is the better one.
    Ambiguous = 1,
    /// No place fits: the scan is from elsewhere, or sees too little of the map.
    NotFound = 2,
}

impl RelocalizeStatus {
    /// Every status, by code.
    pub const ALL: [Self; 3] = [Self::Found, Self::Ambiguous, Self::NotFound];

    /// The status of a wire code.
    pub fn from_code(code: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|s| *s as u32 == code)
    }

    /// Name, as in JSON output.
    pub fn name(self) -> &'static str {
        match self {
            Self::Found => "found",
            Self::Ambiguous => "ambiguous",
            Self::NotFound => "not-found",
        }
    }
}

/// Placements to verify, as `T_map_sensor` with the share of the scan they hit.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Proposal {
    /// Best first.
    pub poses: Vec<(Pose, f64)>,
    /// Points searched with.
    pub points: usize,
    /// Search nodes bounded.
    pub nodes: u64,
    /// The search stopped at its work limit.
    pub exhausted: bool,
    /// The places come from the relief search (uphill ground kept), run because the
    /// structure search proposed none here. Over a tile set a tile's relief places
    /// stand only when no tile proposed from structure, as in one search of the
    /// whole map.
    pub relief: bool,
}

/// The answer of [`relocalize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Relocalization {
    /// The verdict.
    pub status: RelocalizeStatus,
    /// `T_map_sensor` of the best place (identity when nothing was verified).
    pub pose: Pose,
    /// The best place's final registration, when any ran.
    pub result: Option<RegistrationResult>,
    /// Share of the scan paired at the fine distance, best place.
    pub inlier_ratio: f64,
    /// Share paired within `tight-distance` of the fine distance there.
    pub tight_inlier_ratio: f64,
    /// Score of the best place at the verification stage (coarse scan, fine distance).
    pub score: f64,
    /// Same score of the best other place; 0 when there is none.
    pub runner_up: f64,
    /// Places proposed by the search.
    pub candidates: u32,
    /// Registrations run: one settling per proposed place (however many rounds it
    /// took, [`settle_in_rounds`]) and one scoring per distinct place.
    pub registrations: u32,
}

/// Which way is up in a scan's sensor frame, for [`propose`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ScanUp {
    /// The map's z, when the client knows the sensor's tilt (an IMU's gravity, in a
    /// map levelled on gravity).
    Map(Vector3<f64>),
    /// Up found from the scan's own floor-like planes ([`own_up`]); `None` when it has
    /// none within the tilt gate (then nothing is proposed).
    Own(Option<Vector3<f64>>),
}

/// Up from the scan's own floor-like planes, within `params.max_tilt_deg` of its z.
pub fn own_up(scan: &[[f32; 3]], params: &RelocalizeParams) -> Option<Vector3<f64>> {
    estimate_up(scan, params.max_tilt_deg)
}

/// Proposes placements of `scan` (sensor frame, `up` as [`ScanUp`] says) over `grid`,
/// at translations of the grid's region in `columns`; with `peers` (other tiles'
/// searches of the same scan), above their best as [`PeerBest`] says.
pub fn propose(
    grid: &GridView<'_>,
    scan: &[[f32; 3]],
    up: ScanUp,
    columns: Columns<'_>,
    peers: Option<&PeerBest>,
    params: &RelocalizeParams,
) -> Result<Proposal, CloudError> {
    // The grid is levelled on the map's floors: a scan levelled on its own floors is
    // already in that frame; one levelled on the map's z is turned into it per yaw.
    let (up, grid_from_levelled) = match up {
        ScanUp::Map(up) => (up, grid.grid_from_map()),
        ScanUp::Own(Some(up)) => (up, UnitQuaternion::identity()),
        ScanUp::Own(None) => return Ok(Proposal::default()),
    };
    let level = levelling(&up);
    let searched = |ground: Ground, peers| -> Result<SearchOutcome, CloudError> {
        let mut structure = structure_points(scan, &level, grid.resolution(), params, ground)?;
        // Thinned in order of range, not of voxel key: a turned copy of the scan keeps
        // the same points, so its heading does not change what is searched with.
        structure.sort_by(|a, b| {
            a[0].hypot(a[1])
                .total_cmp(&b[0].hypot(b[1]))
                .then(a[2].total_cmp(&b[2]))
        });
        let stride = structure.len().div_ceil(params.search_points).max(1);
        let points: Vec<[f64; 3]> = structure.into_iter().step_by(stride).collect();
        Ok(search(
            grid,
            &points,
            &grid.region(),
            columns,
            peers,
            &params.search,
            &grid_from_levelled,
        ))
    };
    let mut outcome = searched(Ground::Every, peers)?;
    // Too little structure anywhere within reach (open rolling ground): the relief of
    // the ground rising above the sensor is what is left to tell places apart. Not
    // when a peer placed the scan by its structure: then every tile's relief places
    // are left out of the ranking (one search falls back only when it found nothing).
    let relief = outcome.placements.is_empty() && peers.is_none_or(|p| p.ratio() == 0.0);
    if relief {
        let first = outcome;
        outcome = searched(Ground::BelowSensor, None)?;
        outcome.nodes += first.nodes;
        outcome.exhausted |= first.exhausted;
    }
    tracing::debug!(
        "relocalize: searched {} points over {} yaws, {} nodes{}",
        outcome.points,
        outcome.yaws,
        outcome.nodes,
        if outcome.exhausted {
            " (work limit)"
        } else {
            ""
        }
    );
    let map_from_grid: UnitQuaternion<f64> = grid.grid_from_map().inverse();
    for p in &outcome.placements {
        tracing::debug!(
            "relocalize: proposed grid ({:.1}, {:.1}, {:.1}) yaw {:.1} deg, hits {:.3}",
            p.pose.translation.x,
            p.pose.translation.y,
            p.pose.translation.z,
            p.yaw.to_degrees(),
            p.hit_ratio
        );
    }
    Ok(Proposal {
        poses: outcome
            .placements
            .iter()
            .map(|p| (map_from_grid * p.pose * level, p.hit_ratio))
            .collect(),
        points: outcome.points,
        nodes: outcome.nodes,
        exhausted: outcome.exhausted,
        relief,
    })
}

/// Fewest points (voxels) off the ground a search is worth making with.
const MIN_STRUCTURE_POINTS: usize = 100;

/// Which columns' floors [`above_ground`] takes for ground.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ground {
    /// Every column's.
    Every,
    /// Only those below the sensor: ground rising above it (uphill) stays.
    BelowSensor,
}

/// The levelled scan's points a search places: voxelized at the grid's resolution,
/// within range, off the `ground`.
fn structure_points(
    scan: &[[f32; 3]],
    level: &UnitQuaternion<f64>,
    resolution: f64,
    params: &RelocalizeParams,
    ground: Ground,
) -> Result<Vec<[f64; 3]>, CloudError> {
    let mut range = params.max_range;
    loop {
        let in_range: Vec<[f32; 3]> = scan
            .iter()
            .filter(|p| {
                let r = f64::from(p[0]).hypot(f64::from(p[1]));
                r >= params.min_range && r <= range
            })
            .copied()
            .collect();
        let thinned = PointCloud::from_points(in_range).voxel_downsample(resolution)?;
        let levelled: Vec<[f64; 3]> = thinned
            .points
            .iter()
            .map(|p| {
                (level * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))).into()
            })
            .collect();
        let structure = above_ground(&levelled, resolution, ground);
        tracing::debug!(
            "relocalize: {} scan voxels within {range} m, {} off the ground",
            levelled.len(),
            structure.len()
        );
        if structure.len() >= MIN_STRUCTURE_POINTS {
            return Ok(structure);
        }
        if range >= params.max_range * 4.0 {
            return Ok(levelled);
        }
        range *= 2.0;
    }
}

/// `points` (levelled sensor frame) without those of the ground: in each `cell` x
/// `cell` column whose floor (lowest point) `ground` takes for ground, the points less
/// than `cell` above it (terrain may roll; a column's floor is local). Ground lies under
/// every placement at the right height, so it tells places apart by little while it
/// fills most of an outdoor scan's sample. On rolling ground (the simulated campus) the
/// uphill ground is a floor above the sensor: kept as structure, it was 272 of a scan's
/// 296 search points, which then hit marked voxels at places 130 m away more than at
/// its own ([`Ground::Every`] is searched first, [`Ground::BelowSensor`] when that
/// proposes nothing).
pub(super) fn above_ground(points: &[[f64; 3]], cell: f64, ground: Ground) -> Vec<[f64; 3]> {
    let off = off_ground(points, cell, ground);
    points
        .iter()
        .zip(off)
        .filter_map(|(p, off)| off.then_some(*p))
        .collect()
}

/// Which of `points` (levelled: z up) [`above_ground`] keeps: those at least `cell`
/// above the floor of their `cell` x `cell` column, where `ground` takes it for ground.
/// A tracker compares places on these: the ground is alike under every placement.
pub fn off_ground(points: &[[f64; 3]], cell: f64, ground: Ground) -> Vec<bool> {
    let column = |p: &[f64; 3]| [(p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64];
    let mut lowest: HashMap<[i64; 2], f64> = HashMap::new();
    for p in points {
        let z = lowest.entry(column(p)).or_insert(f64::INFINITY);
        *z = z.min(p[2]);
    }
    points
        .iter()
        .map(|p| {
            let floor = lowest[&column(p)];
            (ground == Ground::BelowSensor && floor >= 0.0) || p[2] >= floor + cell
        })
        .collect()
}

/// Azimuth sectors (about the sensor's z) a scan is looked at in by
/// [`verification_selection`]...
const AZIMUTH_SECTORS: usize = 36;
/// ... which takes it to see all around when it has points in this many of them: a
/// spinning LiDAR's scans fill 36 of 36 (balm_os0, KITTI, the simulator), a Livox
/// Avia's 8 (hku2_avia); an operator's body shadows a few.
const ALL_AROUND_SECTORS: usize = 27;

/// The keyframe selection of relocalization's registrations against the map: the map's
/// own (`selection`), without its heading terms when `scan` (sensor frame) sees all
/// around, beyond `min_range` metres. A spinning LiDAR sees a place alike at any
/// heading, so a place's score must not depend on which way the scan faced: with the
/// heading weighed (`rotation-distance-weight`, and the diverse slot's relative
/// headings), a turned copy of a balm_os0 scan registered against keyframes farther
/// away and scored 0.655 instead of 0.751 at its right place (docs/DESIGN.md#notes-relocalization).
/// A narrow-field scan keeps the map's selection: there the heading says what it saw.
pub fn verification_selection(
    scan: &[[f32; 3]],
    selection: &SelectionOptions,
    min_range: f64,
) -> SelectionOptions {
    let mut seen = [false; AZIMUTH_SECTORS];
    for p in scan {
        let (x, y) = (f64::from(p[0]), f64::from(p[1]));
        if x.hypot(y) >= min_range {
            let turn = (y.atan2(x) + PI) / TAU;
            seen[((turn * AZIMUTH_SECTORS as f64) as usize).min(AZIMUTH_SECTORS - 1)] = true;
        }
    }
    if seen.iter().filter(|s| **s).count() < ALL_AROUND_SECTORS {
        return *selection;
    }
    SelectionOptions {
        rotation_distance_weight: 0.0,
        num_diverse_keyframes: 0,
        ..*selection
    }
}

/// The coarse scan (`cloud`, with its covariances `covs`) as places are settled or
/// scored on it: every k-th point, the smallest k leaving at most `points` (0: every
/// point). The covariances come from the whole coarse scan: a kept point's still
/// describes its neighbourhood. Places settle on 1 100 points by default (half of
/// balm_os0's 2 100 coarse points: a third off the scoring phase) and are scored on
/// every coarse point: scoring on 1 000 halved the scoring too, but over a tile set one
/// place's score then stood 0.016 from the merged map's (0.0015 on every coarse point)
/// (docs/DESIGN.md#notes-relocalization).
pub fn thinned_scan(
    cloud: &PointCloud,
    covs: &[PackedSym3],
    points: usize,
) -> (PointCloud, Vec<PackedSym3>) {
    let kept: Vec<usize> = (0..cloud.len())
        .step_by(thinning_stride(cloud.len(), points))
        .collect();
    let covs = kept.iter().filter_map(|&i| covs.get(i).copied()).collect();
    (cloud.select(&kept), covs)
}

/// The k of "every k-th point": the smallest leaving at most `points` of `len` (1 when
/// `points` is 0, every point).
pub fn thinning_stride(len: usize, points: usize) -> usize {
    match points {
        0 => 1,
        n => len.div_ceil(n).max(1),
    }
}

/// Iterations of the scoring registration (coarse scan, fine pairing distance).
const SCORE_ITERATIONS: usize = 10;

/// The stage a place is scored with: the coarse scan at the fine pairing distance.
pub fn score_stage(fine: Stage) -> Stage {
    Stage {
        coarse: true,
        max_pair_dist: fine.max_pair_dist,
        max_iterations: SCORE_ITERATIONS,
    }
}

/// Which step of [`score_places`] a registration of a proposed place runs: each has a
/// scan of its own (`settle-points`, `score-points`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlaceStep {
    /// Coarse iterations from where the search put the place.
    Settle,
    /// Iterations at the fine pairing distance from where it settled; the score.
    Score,
}

/// A proposed place settled by registration and scored.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoredPlace {
    /// Its rank in the search's proposal (0: the best hit ratio).
    pub rank: usize,
    /// Where it settled, `T_map_sensor`.
    pub pose: Pose,
    /// Share of the coarse scan paired at the fine distance there.
    pub score: f64,
}

/// Places scored by [`score_places`], with the registrations it ran.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scored {
    /// In rank order; a place whose registration failed is left out.
    pub places: Vec<ScoredPlace>,
    /// Registrations run: one settling per proposed place (however many rounds it
    /// took, [`settle_in_rounds`]) and one scoring per distinct place.
    pub registrations: u32,
}

/// Settles and scores each proposed place: coarse iterations from it, then
/// [`SCORE_ITERATIONS`] at the fine pairing distance on the coarse scan, whose inlier
/// ratio is the score (places in parallel; `settle(start, stage, step, memo)` runs one
/// registration against the map, `memo` the place's own from its first round to its
/// scoring: the answers of a search, fewer searches). A place that settles within `distinct-m`
/// and `distinct-deg` of a better-ranked one's settled pose is that place: it is not
/// scored again (on balm_os0 nearly half the proposed places settle onto another's).
pub fn score_places<E: Send>(
    proposal: &Proposal,
    fine: Stage,
    tracking: &TrackingParams,
    params: &RelocalizeParams,
    settle: impl Fn(&Pose, &Stage, PlaceStep, &mut NearestMemo) -> Result<Option<RegistrationResult>, E>
    + Sync,
) -> Result<Scored, E> {
    let coarse = Stage {
        coarse: true,
        max_pair_dist: tracking.coarse_pair_dist.max(fine.max_pair_dist),
        max_iterations: tracking.coarse_iterations,
    };
    // Settled at the fine pairing distance before scoring: a place's score must not
    // depend on how well coarse iterations from its lattice yaw happened to converge.
    let score_stage = score_stage(fine);
    let started = std::time::Instant::now();
    let settled = settle_in_rounds(proposal, &coarse, params, &settle)?;
    let settled_at = started.elapsed();
    let mut distinct: Vec<(usize, Pose, NearestMemo)> = Vec::new();
    for (rank, (result, memo)) in settled.into_iter().enumerate() {
        if let Some(result) = result
            && distinct
                .iter()
                .all(|(_, kept, _)| another_place(kept, &result.pose, params))
        {
            distinct.push((rank, result.pose, memo));
        }
    }
    let (scoring, registrations) = (
        distinct.len(),
        (proposal.poses.len() + distinct.len()) as u32,
    );
    let places: Vec<ScoredPlace> = distinct
        .into_par_iter()
        .map(|(rank, pose, mut memo)| {
            Ok(
                settle(&pose, &score_stage, PlaceStep::Score, &mut memo)?.map(|s| ScoredPlace {
                    rank,
                    pose: s.pose,
                    score: s.fitness.inlier_ratio,
                }),
            )
        })
        .collect::<Result<Vec<_>, E>>()?
        .into_iter()
        .flatten()
        .collect();
    tracing::debug!(
        "relocalize: settling {:.1} ms, scoring {} places {:.1} ms",
        settled_at.as_secs_f64() * 1e3,
        scoring,
        (started.elapsed() - settled_at).as_secs_f64() * 1e3
    );
    for place in &places {
        let t = place.pose.translation.vector;
        tracing::debug!(
            "relocalize: rank {} settled at ({:.2}, {:.2}, {:.2}) yaw {:.1} deg, score {:.3}",
            place.rank,
            t.x,
            t.y,
            t.z,
            place.pose.rotation.euler_angles().2.to_degrees(),
            place.score
        );
    }
    Ok(Scored {
        places,
        registrations,
    })
}

/// After its second round, a place still settling whose coarse inlier ratio is this
/// far below the best place's stops and is scored where it is. On balm_os0's revisit
/// the places 0.1 or more below after two rounds ended 0.12-0.35 below the best in
/// score (wrong places wander for up to 20 iterations, or onto a better one), beyond
/// the ambiguity margin (0.05) and the hypotheses' (0.1); rounds 400 -> 312, the same
/// verdicts and places (docs/DESIGN.md#notes-relocalization).
const SETTLE_GIVE_UP: f64 = 0.1;

/// Iterations per round of [`settle_in_rounds`].
const SETTLE_ROUND: usize = 2;

/// Where each proposed place settles: `coarse` iterations from it, every place in
/// rounds of [`SETTLE_ROUND`] iterations (Gauss-Newton keeps no state but the pose, so
/// a place iterates as in one registration). After each round a place within half of
/// `distinct-m` and `distinct-deg` of a better-ranked place still in play is that place
/// and stops (`None`, as a place whose registration failed): a search's places are
/// often the shoulders of one peak 2 m apart (on balm_os0 2.2 of 4.7 places per scan
/// settle onto a better-ranked one's; docs/DESIGN.md#notes-relocalization). After
/// the second round a place pairing [`SETTLE_GIVE_UP`] less than the best stops too,
/// and is scored where it stopped.
fn settle_in_rounds<E: Send>(
    proposal: &Proposal,
    coarse: &Stage,
    params: &RelocalizeParams,
    settle: &(
         impl Fn(&Pose, &Stage, PlaceStep, &mut NearestMemo) -> Result<Option<RegistrationResult>, E>
         + Sync
     ),
) -> Result<Vec<(Option<RegistrationResult>, NearestMemo)>, E> {
    /// One place's settling so far.
    struct Settling {
        result: Option<RegistrationResult>,
        start: Pose,
        iterations: usize,
        running: bool,
        /// Its points' nearest map points, from round to round (the scoring's too).
        memo: NearestMemo,
    }
    let mut places: Vec<Settling> = proposal
        .poses
        .iter()
        .map(|(start, _)| Settling {
            result: None,
            start: *start,
            iterations: 0,
            running: true,
            memo: NearestMemo::default(),
        })
        .collect();
    let same = |a: &Pose, b: &Pose| {
        translation_distance(a, b) <= params.distinct_m / 2.0
            && rotation_distance(a, b).to_degrees() <= params.distinct_deg / 2.0
    };
    let (mut rounds, mut merged) = (0, 0);
    while places.iter().any(|p| p.running) {
        rounds += 1;
        places
            .par_iter_mut()
            .filter(|p| p.running)
            .try_for_each(|place| -> Result<(), E> {
                let round = SETTLE_ROUND.min(coarse.max_iterations - place.iterations);
                let stage = Stage {
                    max_iterations: round,
                    ..*coarse
                };
                let result = settle(&place.start, &stage, PlaceStep::Settle, &mut place.memo)?;
                let iterations = result.as_ref().map_or(0, |r| r.iterations);
                place.iterations += round;
                // Converged, stopped on a step it could not take, or out of iterations.
                place.running = result.as_ref().is_some_and(|r| {
                    !r.converged && iterations == round && place.iterations < coarse.max_iterations
                });
                if let Some(r) = &result {
                    place.start = r.pose;
                }
                place.result = result;
                Ok(())
            })?;
        // From the second round on, a place pairing far less of the coarse scan than
        // the best one stops where it is and is scored there (see `SETTLE_GIVE_UP`).
        if rounds >= 2 {
            let ratio = |p: &Settling| p.result.as_ref().map(|r| r.fitness.inlier_ratio);
            let best = places.iter().filter_map(ratio).fold(0.0, f64::max);
            for place in places.iter_mut().filter(|p| p.running) {
                place.running = ratio(place).is_none_or(|r| r + SETTLE_GIVE_UP >= best);
            }
        }
        for later in 1..places.len() {
            let (better, rest) = places.split_at_mut(later);
            let place = &mut rest[0];
            let Some(at) = place.result.as_ref().map(|r| r.pose) else {
                continue;
            };
            let merged_here = better
                .iter()
                .any(|b| b.result.as_ref().is_some_and(|r| same(&r.pose, &at)));
            if merged_here {
                place.running = false;
                place.result = None;
                merged += 1;
            }
        }
    }
    tracing::debug!(
        "relocalize: settled {} places in {rounds} rounds, {} iterations, {merged} onto a better one",
        places.len(),
        places.iter().map(|p| p.iterations).sum::<usize>()
    );
    Ok(places.into_iter().map(|p| (p.result, p.memo)).collect())
}

/// True when `b` is another place than `a`: farther than `distinct-m` or turned more
/// than `distinct-deg` (a runner-up counts only then).
pub fn another_place(a: &Pose, b: &Pose, params: &RelocalizeParams) -> bool {
    translation_distance(a, b) > params.distinct_m
        || rotation_distance(a, b).to_degrees() > params.distinct_deg
}

/// Whether every place of `near` (scored within the margin of `best`'s place) only
/// slides where `best` is pinned: `best` loses at least `pinned-share` under the slide,
/// and each other place, registered again as it was scored (`rescore`: a few
/// iterations, where the whole scan's fine ones took 7-29 along a slide on balm_os0),
/// loses less and explains at least `explained-lead` less, give or take
/// [`Pinning::share_noise`]. A place that no longer
/// fits, or settles onto `best`, is no rival. Counts the registrations in `answer`.
fn only_slides<E>(
    best: &RegistrationResult,
    near: &[Pose],
    params: &RelocalizeParams,
    answer: &mut Relocalization,
    mut rescore: impl FnMut(&Pose) -> Result<Option<RegistrationResult>, E>,
    mut pinning: impl FnMut(&RegistrationResult) -> Result<Pinning, E>,
) -> Result<bool, E> {
    if params.pinned_share <= 0.0 {
        return Ok(false);
    }
    let pinned = pinning(best)?;
    if pinned.slide_loss.is_none_or(|l| l < params.pinned_share) {
        return Ok(false);
    }
    for place in near {
        answer.registrations += 1;
        let Some(other) = rescore(place)? else {
            continue;
        };
        if !another_place(&other.pose, &best.pose, params) {
            continue;
        }
        tracing::debug!(
            "relocalize: a rival registered in {} iterations",
            other.iterations
        );
        let other = pinning(&other)?;
        let slides = other.slide_loss.is_some_and(|l| l < params.pinned_share);
        let explains_more =
            other.explained + params.explained_lead > pinned.explained + pinned.share_noise();
        if !slides || explains_more {
            return Ok(false);
        }
    }
    Ok(true)
}

/// What a place's structure shows of the map ([`super::pinning`]): the share explained
/// there and what a slide along its weakest direction loses of it (`None` without a
/// covariance).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinning {
    /// Share of the scan's structure with a map point within `tight-distance`.
    pub explained: f64,
    /// What a 0.5 m slide loses of it, at the worse side.
    pub slide_loss: Option<f64>,
    /// Structure points the share is of.
    pub points: usize,
}

impl Pinning {
    /// Two standard errors of `explained` as a share of `points` draws: shares closer
    /// than this do not tell two places apart.
    pub fn share_noise(&self) -> f64 {
        let p = self.explained.clamp(0.0, 1.0);
        2.0 * (p * (1.0 - p) / self.points.max(1) as f64).sqrt()
    }
}

/// The best of `scored` (the first of equal scores) gets fine iterations; it fits when
/// it pairs at least `found-inlier-ratio` of the scan at the fine distance and
/// `found-tight-ratio` within `tight-distance` of it, with a covariance. A fitting
/// place is `found` unless a place more than `distinct-m` / `distinct-deg` away scores
/// within `ambiguity-margin` of it (`ambiguous`), or every such place only slides
/// where the best is pinned (`pinned-share`: `pinning` measures a registered place,
/// `rescore` registers another place again as it was scored); else the answer is
/// `not-found`. `candidates`: places the search proposed.
pub fn decide<E>(
    scored: &Scored,
    candidates: u32,
    fine: Stage,
    params: &RelocalizeParams,
    mut register: impl FnMut(&Pose, &Stage) -> Result<Option<RegistrationResult>, E>,
    rescore: impl FnMut(&Pose) -> Result<Option<RegistrationResult>, E>,
    pinning: impl FnMut(&RegistrationResult) -> Result<Pinning, E>,
) -> Result<Relocalization, E> {
    let mut ranked: Vec<(Pose, f64)> = scored.places.iter().map(|p| (p.pose, p.score)).collect();
    ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut answer = Relocalization {
        status: RelocalizeStatus::NotFound,
        pose: Pose::identity(),
        result: None,
        inlier_ratio: 0.0,
        tight_inlier_ratio: 0.0,
        score: 0.0,
        runner_up: 0.0,
        candidates,
        registrations: scored.registrations,
    };
    let Some(&(start, score)) = ranked.first() else {
        return Ok(answer);
    };
    answer.registrations += 1;
    let started = std::time::Instant::now();
    let Some(result) = register(&start, &fine)? else {
        return Ok(answer);
    };
    let registered = started.elapsed();
    let rivals: Vec<(Pose, f64)> = ranked
        .iter()
        .skip(1)
        .filter(|(p, _)| another_place(p, &result.pose, params))
        .copied()
        .collect();
    answer.runner_up = rivals.iter().map(|(_, s)| *s).fold(0.0, f64::max);
    answer.pose = result.pose;
    answer.score = score;
    answer.inlier_ratio = result.fitness.inlier_ratio;
    answer.result = Some(result);
    // A place fits when the scan lies on its surfaces, not merely near them.
    let tight = Stage {
        coarse: false,
        max_pair_dist: fine.max_pair_dist * params.tight_distance,
        max_iterations: 1,
    };
    answer.registrations += 1;
    answer.tight_inlier_ratio =
        register(&result.pose, &tight)?.map_or(0.0, |r| r.fitness.inlier_ratio);
    tracing::debug!(
        "relocalize: the best place registered in {} iterations, {:.1} ms; its tight fit {:.1} ms",
        result.iterations,
        registered.as_secs_f64() * 1e3,
        (started.elapsed() - registered).as_secs_f64() * 1e3
    );
    let fits = result.fitness.inlier_ratio >= params.found_inlier_ratio
        && answer.tight_inlier_ratio >= params.found_tight_ratio
        && pose_covariance(&result).is_some();
    answer.status = if !fits {
        RelocalizeStatus::NotFound
    } else if answer.runner_up + params.ambiguity_margin < score {
        RelocalizeStatus::Found
    } else {
        let near: Vec<Pose> = rivals
            .iter()
            .filter(|(_, s)| s + params.ambiguity_margin >= score)
            .map(|(p, _)| *p)
            .collect();
        if only_slides(&result, &near, params, &mut answer, rescore, pinning)? {
            RelocalizeStatus::Found
        } else {
            RelocalizeStatus::Ambiguous
        }
    };
    Ok(answer)
}
