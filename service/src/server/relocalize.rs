//! `Relocalize`: where a scan was taken, with no pose guess. The search runs on the
//! map's baked place grid; each proposed place is verified by the same registrations
//! as `Localize`, against the served map in the client's session. Over a tile set the
//! client runs the steps as three phases, one request each (docs/DESIGN.md#notes-tiles):
//! places, scores of the chosen places, the final registration of the best.

use std::sync::{Arc, Mutex, PoisonError};

use kfmap_geometry::geometry::{PackedSym3, Pose, to_point, transform_point};
use kfmap_geometry::registration::RegistrationResult;
use kfmap_geometry::tracking::{covariance_to_wire, pose_covariance};
use kfmap_map::map::NearestMemo;
use kfmap_map::place::pinning::{slide_loss, structure};
use kfmap_map::place::{
    Columns, GridView, PeerBest, Pinning, PlaceStep, Proposal, Relocalization, RelocalizeParams,
    RelocalizeStatus, ScanUp, Scored, ScoredPlace, decide, own_up, propose, score_places,
    score_stage, thinned_scan, thinning_stride, verification_selection,
};
use kfmap_protocol::{
    DecodedScan, FLAG_FINISH_CHOSEN, FLAG_LEVELLED, FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN,
    PLACES_FROM_RELIEF, Rejection, RequestHeader, StatusCode, place_to_wire, pose_to_wire,
};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::answer::{Answer, AnswerPairings, bad, exact_mode, map_error, with_active};
use super::limits::Limits;
use super::localize::localize_params;
use super::queries::Activation;
use super::register::{MapRegistration, coarse_error, prepare, register_approximate};
use super::session::{ProposedFor, Session};
use super::state::ServedMap;

/// What a `Relocalize` request asks of the steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Search, score, decide: a relocalization on one server.
    Whole,
    /// `FLAG_PLACES_ONLY`: the search's places.
    Places,
    /// `FLAG_SCORE_CHOSEN`: the chosen places (rank bits) settled and scored.
    Score(u64),
    /// `FLAG_FINISH_CHOSEN`: the final registration of the scored place of this rank.
    Finish(usize),
}

impl Phase {
    fn of(request: &RequestHeader) -> Result<Self, Rejection> {
        let ranks = request.keyframe_or_scan_id;
        let flags = request.flags & (FLAG_PLACES_ONLY | FLAG_SCORE_CHOSEN | FLAG_FINISH_CHOSEN);
        match flags {
            0 => Ok(Self::Whole),
            FLAG_PLACES_ONLY => Ok(Self::Places),
            FLAG_SCORE_CHOSEN if ranks != 0 => Ok(Self::Score(ranks)),
            FLAG_SCORE_CHOSEN => Err(bad(
                "FLAG_SCORE_CHOSEN with no place chosen: set bit r of keyframe_or_scan_id to score the r-th best place",
            )),
            FLAG_FINISH_CHOSEN if ranks.count_ones() == 1 => {
                Ok(Self::Finish(ranks.trailing_zeros() as usize))
            }
            FLAG_FINISH_CHOSEN => Err(bad(format!(
                "FLAG_FINISH_CHOSEN finishes one place: set exactly one bit of keyframe_or_scan_id, not {ranks:#x}"
            ))),
            _ => Err(bad(
                "FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN and FLAG_FINISH_CHOSEN are phases: set one at a time",
            )),
        }
    }
}

/// Answers a `Relocalize` request; `pose` is the guess, whose rotation levels the scan
/// when the request carries `FLAG_LEVELLED`.
pub fn relocalize(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    scan: &DecodedScan,
    pose: &Pose,
    limits: &Limits,
) -> Result<Answer, Rejection> {
    let phase = Phase::of(request)?;
    let (fine, _) = localize_params(request)?;
    let exact = exact_mode(map, request.mode, limits)?;
    let grid = map
        .place
        .as_ref()
        .ok_or_else(|| {
            Rejection::new(
                StatusCode::BadRequest,
                "this map has no place grid (baked by an older kfmap): bake the map again to relocalize",
            )
        })?
        .view()
        .map_err(|e| Rejection::new(StatusCode::Internal, format!("map: {e}")))?;
    let params = limits.relocalize;
    // The map's z in the sensor frame: the guess's tilt (`R_map_sensor` up to yaw) when
    // the client knows it; otherwise the search levels the scan on its own floors.
    let map_up =
        (request.flags & FLAG_LEVELLED != 0).then(|| pose.rotation.inverse() * Vector3::z());
    let started = std::time::Instant::now();
    // The session keeps one scan's places (and scores) between the phases; the steps
    // are deterministic, so a lost session only costs running them again. A plain
    // relocalization neither reads nor keeps them.
    let kept = match phase {
        Phase::Score(_) | Phase::Finish(_) => session
            .last_places
            .take()
            .filter(|p| p.points == scan.points && p.map_up == map_up),
        Phase::Whole | Phase::Places => None,
    };
    // The final registration's scan (thinned to `final-points`, its covariances
    // estimated on what is kept) and the candidates' coarse one: each a copy with
    // covariances, built once on first use.
    let final_thinned = ThinnedScan::of(scan, params.final_points);
    let final_scan = final_thinned.as_ref().map(ThinnedScan::scan);
    let mut stages = prepare(final_scan.as_ref().unwrap_or(scan), limits);
    let mut candidates = prepare(scan, limits);
    let (points, proposal, scored) = match kept {
        Some(kept) => (Some(kept.points), kept.proposal, kept.scored),
        None if phase == Phase::Whole => {
            // Both scans are built while the search runs: its batches of bounds leave
            // a core idle much of the time (docs/DESIGN.md#notes-relocalization).
            let (proposal, ()) = rayon::join(
                || proposed(&grid, map, scan.points, map_up, phase, &params),
                || {
                    stages.fine();
                    // A failure shows where the coarse scan is used, below.
                    let _ = candidates.coarse();
                },
            );
            (None, proposal?, None)
        }
        None => (
            None,
            proposed(&grid, map, scan.points, map_up, phase, &params)?,
            None,
        ),
    };
    let remember = |proposal: Proposal, scored: Option<Scored>| ProposedFor {
        points: points.unwrap_or_else(|| scan.points.to_vec()),
        map_up,
        proposal,
        scored,
    };
    let searched = started.elapsed();
    if phase == Phase::Places {
        let answer = places_answer(&proposal, params.search.candidates);
        session.last_places = Some(remember(proposal, None));
        return Ok(answer);
    }
    // Every registration of a place (scoring and the final one) pairs with the
    // keyframes the scan's field of view makes relevant there.
    let activation = Activation {
        selection: verification_selection(
            scan.points,
            &map.map.options().selection,
            params.min_range,
        ),
        exact,
    };
    let mut against = MapRegistration {
        map,
        session,
        activation,
        active: Vec::new(),
    };
    // The candidates' coarse registrations run in parallel, so they share a coarse
    // scan of their own; the ladder's stages build theirs on first use. Finishing a
    // place this session scored settles nothing: no coarse scan then.
    let kept_place = match phase {
        Phase::Finish(rank) => scored
            .as_ref()
            .and_then(|s| s.places.iter().find(|p| p.rank == rank).copied()),
        Phase::Whole | Phase::Places | Phase::Score(_) => None,
    };
    let coarse = match kept_place {
        Some(_) => None,
        None => Some(candidates.coarse().map_err(coarse_error)?),
    };
    // Places are settled and scored on the coarse scan, thinned when `settle-points`
    // and `score-points` ask for fewer points than it has (copied only then).
    let thinned = |points: usize| {
        coarse
            .filter(|(cloud, _)| points > 0 && cloud.len() > points)
            .map(|(cloud, covs)| thinned_scan(cloud, covs, points))
    };
    let (to_settle, to_score) = (thinned(params.settle_points), thinned(params.score_points));
    let settle_scan = to_settle
        .as_ref()
        .map(|(c, v)| (c, v.as_slice()))
        .or(coarse);
    let score_scan = to_score.as_ref().map(|(c, v)| (c, v.as_slice())).or(coarse);
    let settle = |start: &Pose, stage: &_, step, memo: &mut NearestMemo| {
        let scan = match step {
            PlaceStep::Settle => settle_scan,
            PlaceStep::Score => score_scan,
        };
        let (cloud, covs) =
            scan.ok_or_else(|| Rejection::new(StatusCode::Internal, "no coarse scan"))?;
        register_approximate(map, &activation.selection, cloud, covs, start, stage, memo)
    };
    let scored_ranks = |ranks: u64| -> Result<Scored, Rejection> {
        let (chosen, of) = chosen_places(&proposal, ranks)?;
        let mut scored = score_places(&chosen, fine, &limits.tracking, &params, settle)?;
        for place in &mut scored.places {
            place.rank = of[place.rank];
        }
        Ok(scored)
    };
    let register = |start: &Pose, stage: &_| {
        let (cloud, covs) = stages.for_stage(stage).map_err(coarse_error)?;
        against.register(cloud, covs, start, stage)
    };
    // A rival of the best is registered again as it was scored: on the scoring scan.
    let rescore = |place: &Pose| {
        settle(
            place,
            &score_stage(fine),
            PlaceStep::Score,
            &mut NearestMemo::default(),
        )
    };
    let tight = fine.max_pair_dist * params.tight_distance;
    let pinned = |result: &RegistrationResult| pinning(map, scan.points, tight, result);
    let found = match phase {
        Phase::Places => unreachable!("answered above"),
        Phase::Whole => {
            let every = score_places(&proposal, fine, &limits.tracking, &params, settle)?;
            let scored_at = started.elapsed();
            let found = decide(
                &every,
                proposal.poses.len() as u32,
                fine,
                &params,
                register,
                rescore,
                pinned,
            )?;
            tracing::debug!(
                "relocalize: scoring {} places {:.1} ms, final registration {:.1} ms",
                every.places.len(),
                (scored_at - searched).as_secs_f64() * 1e3,
                (started.elapsed() - scored_at).as_secs_f64() * 1e3
            );
            log_verdict(searched, started, &found);
            // Every scored place travels with the verdict: a tracker keeps the ones
            // close to the best as hypotheses to tell apart on the next scans.
            return Ok(verdict_answer(&found, &against.active, &every.places));
        }
        Phase::Score(ranks) => {
            let chosen = scored_ranks(ranks)?;
            let answer = scored_answer(&chosen, ranks.count_ones());
            against.session.last_places = Some(remember(proposal, Some(chosen)));
            return Ok(answer);
        }
        Phase::Finish(rank) => {
            let lone = match kept_place {
                Some(place) => Scored {
                    places: vec![place],
                    registrations: 0,
                },
                None => scored_ranks(1 << rank)?,
            };
            let mut found = decide(&lone, 1, fine, &params, register, rescore, pinned)?;
            // Alone it has no runner-up: it is found when it fits; the client that
            // chose it judges ambiguity over every tile's scores.
            if found.status == RelocalizeStatus::Ambiguous {
                found.status = RelocalizeStatus::Found;
            }
            against.session.last_places = Some(remember(proposal, scored));
            found
        }
    };
    log_verdict(searched, started, &found);
    Ok(verdict_answer(&found, &against.active, &[]))
}

/// Every k-th point of a scan as sent ([`thinning_stride`], as the coarse scan is
/// thinned), with its view directions and any covariances the client sent.
struct ThinnedScan {
    points: Vec<[f32; 3]>,
    view_dirs: Option<Vec<[f32; 3]>>,
    covariances: Option<Vec<PackedSym3>>,
}

impl ThinnedScan {
    /// `None` when `scan` has at most `points` points or `points` is 0 (every point).
    fn of(scan: &DecodedScan, points: usize) -> Option<Self> {
        let n = scan.points.len();
        if points == 0 || n <= points {
            return None;
        }
        let stride = thinning_stride(n, points);
        let thin = |v: &[[f32; 3]]| v.iter().step_by(stride).copied().collect::<Vec<_>>();
        Some(Self {
            points: thin(scan.points),
            view_dirs: scan.view_dirs.map(thin),
            covariances: scan
                .covariances
                .map(|c| c.iter().step_by(stride).copied().collect()),
        })
    }

    fn scan(&self) -> DecodedScan<'_> {
        DecodedScan {
            points: &self.points,
            view_dirs: self.view_dirs.as_deref(),
            covariances: self.covariances.as_deref(),
        }
    }
}

/// [`Pinning`] of a registered place: the scan's structure there, and a slide along
/// the registration's least constrained horizontal direction, each measured by
/// nearest neighbours in the keyframes the map selects at the pose, as the tracker's
/// slide probe measures it (`tight`: the distance a point is explained within). The
/// tracker's own explained share searches the keyframes around the pose instead; the
/// verdict's `explained-lead` and `pinned-share` were measured on the active set and
/// stay there.
fn pinning(
    map: &ServedMap,
    points: &[[f32; 3]],
    tight: f64,
    result: &RegistrationResult,
) -> Result<Pinning, Rejection> {
    let started = std::time::Instant::now();
    let structure = structure(points, &result.pose);
    let explained_at = |at: &Pose| explained_share(map, &structure, at, tight);
    let explained = explained_at(&result.pose)?;
    let slide_loss = match pose_covariance(result) {
        Some(covariance) => slide_loss(&result.pose, &covariance, explained, explained_at)?,
        None => None,
    };
    tracing::debug!(
        "relocalize: pinning of {} structure points {:.1} ms: explained {explained:.3}, slide loss {slide_loss:?}",
        structure.len(),
        started.elapsed().as_secs_f64() * 1e3
    );
    Ok(Pinning {
        explained,
        slide_loss,
        points: structure.len(),
    })
}

/// The share of `structure` (sensor frame) with a map point within `tight` metres at
/// `pose`.
fn explained_share(
    map: &ServedMap,
    structure: &[[f32; 3]],
    pose: &Pose,
    tight: f64,
) -> Result<f64, Rejection> {
    let ids = map.map.select_with(pose, &map.map.options().selection);
    let active = map
        .map
        .activate_cached(ids, &mut None, false)
        .map_err(map_error)?;
    let tight_sq = (tight * tight) as f32;
    let explained = structure
        .par_iter()
        .filter(|p| {
            let q = to_point(&transform_point(pose, p));
            active
                .nearest_one(&q)
                .is_some_and(|hit| hit.dist_sq <= tight_sq)
        })
        .count();
    Ok(explained as f64 / structure.len().max(1) as f64)
}

/// Logs a verdict's phases at debug: the search's time, the verification's, the verdict.
fn log_verdict(searched: std::time::Duration, started: std::time::Instant, found: &Relocalization) {
    tracing::debug!(
        "relocalize: search {:.1} ms, verify {:.1} ms ({} registrations): {}",
        searched.as_secs_f64() * 1e3,
        (started.elapsed() - searched).as_secs_f64() * 1e3,
        found.registrations,
        found.status.name()
    );
}

/// The search's places for `scan`: up from the client's tilt, else from its floors.
/// The phases of a search over a tile set try only the tile's share of the
/// translations, so that the tiles together try each once; a whole relocalization
/// on a tile tries its whole region.
fn proposed(
    grid: &GridView<'_>,
    map: &ServedMap,
    scan: &[[f32; 3]],
    map_up: Option<Vector3<f64>>,
    phase: Phase,
    params: &RelocalizeParams,
) -> Result<Proposal, Rejection> {
    let up = match map_up {
        Some(up) => ScanUp::Map(up),
        // Only the first phase fans one scan out to every tile at once.
        None if phase == Phase::Places => ScanUp::Own(shared_own_up(scan, params)),
        None => ScanUp::Own(own_up(scan, params)),
    };
    let (columns, peers) = match (phase, map.share_columns(grid)) {
        (Phase::Whole, _) | (_, None) => (Columns::All, None),
        (Phase::Places | Phase::Score(_) | Phase::Finish(_), Some(table)) => {
            (Columns::Owned(table), Some(scan_peers(scan, map_up)))
        }
    };
    propose(grid, scan, up, columns, peers.as_deref(), params)
        .map_err(|e| bad(format!("scan: {e}")))
}

/// What the tiles one process serves share about the scan they were last asked to
/// place: over a tile set the client asks every tile with the same scan at once
/// (docs/DESIGN.md#notes-tiles).
struct SharedScan {
    points: Vec<[f32; 3]>,
    /// The client's tilt, when it sent one.
    map_up: Option<Vector3<f64>>,
    /// Up from the scan's floors and the tilt gate it was found under: found once for
    /// every tile (most of a tile's first phase when the scan fits nowhere).
    own_up: Option<(f64, Option<Vector3<f64>>)>,
    /// The best of the tiles' searches: one that finds a place lets the others stop
    /// looking below what the client keeps ([`PeerBest`]).
    peers: Arc<PeerBest>,
}

/// The last scan's [`SharedScan`] in this process.
static LAST_SCAN: Mutex<Option<SharedScan>> = Mutex::new(None);

/// Runs `f` on the [`SharedScan`] of `scan` (levelled by `map_up`), a fresh one for a
/// new scan, with the lock held: a tile asking with the same scan meanwhile waits and
/// reads what `f` found.
fn with_shared_scan<R>(
    scan: &[[f32; 3]],
    map_up: Option<Vector3<f64>>,
    f: impl FnOnce(&mut SharedScan) -> R,
) -> R {
    let mut last = LAST_SCAN.lock().unwrap_or_else(PoisonError::into_inner);
    let same = last
        .as_ref()
        .is_some_and(|s| s.points == scan && s.map_up == map_up);
    if !same {
        *last = Some(SharedScan {
            points: scan.to_vec(),
            map_up,
            own_up: None,
            peers: Arc::new(PeerBest::default()),
        });
    }
    f(last.as_mut().expect("set above"))
}

/// The searches of `scan` (levelled by `map_up`) in this process.
fn scan_peers(scan: &[[f32; 3]], map_up: Option<Vector3<f64>>) -> Arc<PeerBest> {
    with_shared_scan(scan, map_up, |shared| Arc::clone(&shared.peers))
}

/// [`own_up`] of `scan`, shared by the maps this process serves.
fn shared_own_up(scan: &[[f32; 3]], params: &RelocalizeParams) -> Option<Vector3<f64>> {
    with_shared_scan(scan, None, |shared| match shared.own_up {
        Some((tilt, up)) if tilt == params.max_tilt_deg => up,
        _ => {
            let up = own_up(scan, params);
            shared.own_up = Some((params.max_tilt_deg, up));
            up
        }
    })
}

/// The answer of a decided relocalization, with the scored `places` in the pairings'
/// slots ([`place_slots`]).
fn verdict_answer(found: &Relocalization, active: &[u64], places: &[ScoredPlace]) -> Answer {
    let mut answer = with_active(AnswerPairings::Wire(place_slots(places)), active);
    let h = &mut answer.header;
    h.relocalization = found.status as u32;
    h.candidates = found.candidates;
    h.place_scores = [found.score, found.runner_up];
    h.tight_fitness = found.tight_inlier_ratio;
    h.registrations = found.registrations;
    let result = found.result;
    h.fitness = [found.inlier_ratio, result.map_or(0.0, |r| r.fitness.rmse)];
    if let Some(result) = result.filter(|_| found.status != RelocalizeStatus::NotFound) {
        h.pose = pose_to_wire(&found.pose);
        h.covariance = covariance_to_wire(pose_covariance(&result).as_ref());
        h.iterations = result.iterations as u32;
        h.converged = result.converged as u32;
        h.degenerate = result.degenerate as u32;
        h.constraint = [
            result.constraint.rotation_ratio,
            result.constraint.translation_ratio,
        ];
    }
    answer
}

/// The places of `proposal` whose ranks are set in `ranks` (bit r: rank r), best first,
/// and the rank each came from.
fn chosen_places(proposal: &Proposal, ranks: u64) -> Result<(Proposal, Vec<usize>), Rejection> {
    let proposed = proposal.poses.len();
    let highest = 63 - ranks.leading_zeros() as usize;
    if highest >= proposed {
        return Err(bad(format!(
            "the place of rank {highest} was chosen, but this scan's search proposed {proposed}"
        )));
    }
    let of: Vec<usize> = (0..proposed).filter(|r| ranks & (1 << r) != 0).collect();
    let poses = of.iter().map(|&r| proposal.poses[r]).collect();
    Ok((
        Proposal {
            poses,
            ..proposal.clone()
        },
        of,
    ))
}

/// A `FLAG_PLACES_ONLY` answer: the places in the pairings' slots, best first;
/// `candidates` counts them, `place_scores` holds the best two hit ratios and `detail`
/// the places one search verifies here (`[relocalize.search] candidates`), which the
/// client takes as many of over every tile. Nothing is verified: `not-found`.
fn places_answer(proposal: &Proposal, verified_per_search: usize) -> Answer {
    let places: Vec<_> = proposal
        .poses
        .iter()
        .enumerate()
        .map(|(rank, (pose, hits))| place_to_wire(pose, *hits, rank).to_slot())
        .collect();
    let mut answer = with_active(AnswerPairings::Wire(places), &[]);
    let h = &mut answer.header;
    h.relocalization = RelocalizeStatus::NotFound as u32;
    h.candidates = proposal.poses.len() as u32;
    let score = |rank: usize| proposal.poses.get(rank).map_or(0.0, |(_, hits)| *hits);
    h.place_scores = [score(0), score(1)];
    h.detail = verified_per_search as u64;
    h.reasons = if proposal.relief {
        PLACES_FROM_RELIEF
    } else {
        0
    };
    answer
}

/// Scored places as [`kfmap_protocol::WirePlace`]s in pairings' slots, in rank order:
/// settled pose, score, rank.
fn place_slots(places: &[ScoredPlace]) -> Vec<kfmap_protocol::WirePairing> {
    places
        .iter()
        .map(|p| place_to_wire(&p.pose, p.score, p.rank).to_slot())
        .collect()
}

/// A `FLAG_SCORE_CHOSEN` answer: the chosen places that settled (pose, score, rank) in
/// rank order; `candidates` the places chosen, `registrations` those run. Nothing is
/// decided: `not-found`.
fn scored_answer(scored: &Scored, chosen: u32) -> Answer {
    let mut answer = with_active(AnswerPairings::Wire(place_slots(&scored.places)), &[]);
    let h = &mut answer.header;
    h.relocalization = RelocalizeStatus::NotFound as u32;
    h.candidates = chosen;
    h.registrations = scored.registrations;
    answer
}
