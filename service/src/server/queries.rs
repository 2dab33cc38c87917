//! Map queries of one scan: nearest neighbours, radius search and cov2cov pairings in
//! the active keyframes at the scan's pose (nearest neighbours also in the keyframes
//! around it), each capped so an answer never outgrows the server's limits.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{Pose, to_point, transform_point};
use kfmap_map::map::{ActiveSet, MapHit, Pairing};
use kfmap_map::select::SelectionOptions;
use kfmap_protocol::{
    DecodedScan, Rejection, RequestHeader, ResponseHeader, StatusCode, WirePairing,
};
use rayon::prelude::*;

use super::answer::{Answer, AnswerPairings, bad, map_error, with_active};
use super::limits::{Limits, MAX_K, MAX_KEYFRAMES, MAX_PAIR_DIST, MAX_RADIUS, PAIRING_BYTES};
use super::session::Session;
use super::state::ServedMap;

/// A no-work answer: the header only, `detail` = points received (round trips).
pub(super) fn echo(
    request: &RequestHeader,
    payload: &[f32],
    limits: &Limits,
) -> Result<Answer, Rejection> {
    let n = (request.point_count as usize).min(payload.len() / 3);
    if n > limits.max_points {
        return Err(Rejection::new(
            StatusCode::TooManyPoints,
            format!("{n} points; at most {}", limits.max_points),
        ));
    }
    Ok(Answer {
        header: ResponseHeader {
            detail: n as u64,
            ..Default::default()
        },
        pairings: AnswerPairings::default(),
    })
}

/// How a query's active keyframes are chosen and searched.
#[derive(Debug, Clone, Copy)]
pub(super) struct Activation {
    /// Keyframe selection at the query's pose: the map's own, or relocalization's
    /// ([`kfmap_map::place::verification_selection`]).
    pub(super) selection: SelectionOptions,
    /// Exact cov2cov: a merged submap of the active keyframes, cached in the session.
    pub(super) exact: bool,
}

impl Activation {
    /// The map's own selection.
    pub(super) fn of_map(map: &ServedMap, exact: bool) -> Self {
        Self {
            selection: map.map.options().selection,
            exact,
        }
    }
}

/// The active set for a query at `pose`, with the session's merged-submap cache.
fn activate<'m>(
    map: &'m ServedMap,
    session: &mut Session,
    pose: &Pose,
    activation: Activation,
) -> Result<ActiveSet<'m>, Rejection> {
    let ids = map.map.select_with(pose, &activation.selection);
    activate_ids(map, session, ids, activation.exact)
}

/// The active set of exactly `ids` (none: the map is empty), with the session's
/// merged-submap cache.
fn activate_ids<'m>(
    map: &'m ServedMap,
    session: &mut Session,
    ids: Vec<KeyframeId>,
    exact: bool,
) -> Result<ActiveSet<'m>, Rejection> {
    if ids.is_empty() {
        return Err(Rejection::new(
            StatusCode::MapNotLoaded,
            "the map has no keyframes",
        ));
    }
    map.map
        .activate_cached(ids, &mut session.merged, exact)
        .map_err(map_error)
}

fn to_map_frame(pose: &Pose, p: &[f32; 3]) -> [f32; 3] {
    to_point(&transform_point(pose, p))
}

/// Why a search stopped before the end of the scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Overflow {
    /// This scan point found more than its cap.
    Point(usize),
    /// The answer grew past its cap of pairings.
    Total,
}

/// Caps on one search's answer, checked as it grows.
#[derive(Debug, Clone, Copy)]
struct Caps {
    per_point: usize,
    total: usize,
}

/// Every scan point moved by `pose` and searched by `search` in `active`: the hits as
/// pairings without information, in query order. The search stops once a point finds
/// more than `caps.per_point` or the answer more than `caps.total`, so the answer never
/// outgrows them.
fn search_each(
    active: &ActiveSet,
    scan: &DecodedScan,
    pose: &Pose,
    caps: Caps,
    search: impl Fn(&ActiveSet, &[f32; 3]) -> Vec<MapHit> + Sync,
) -> Result<Answer, Overflow> {
    let (over_point, over_total) = (AtomicUsize::new(usize::MAX), AtomicBool::new(false));
    let found = AtomicUsize::new(0);
    let pairings: Vec<WirePairing> = scan
        .points
        .par_iter()
        .enumerate()
        .flat_map_iter(|(i, p)| {
            let stopped = over_point.load(Ordering::Relaxed) != usize::MAX
                || over_total.load(Ordering::Relaxed);
            let mut hits = if stopped {
                Vec::new()
            } else {
                search(active, &to_map_frame(pose, p))
            };
            if hits.len() > caps.per_point {
                over_point.fetch_min(i, Ordering::Relaxed);
                hits.clear();
            } else if found.fetch_add(hits.len(), Ordering::Relaxed) + hits.len() > caps.total {
                over_total.store(true, Ordering::Relaxed);
                hits.clear();
            }
            hits.into_iter().map(move |h| WirePairing {
                query: i as u32,
                local_index: h.local_index,
                keyframe: h.keyframe,
                point: h.point,
                dist_sq: h.dist_sq,
                information: [0.0; 6],
            })
        })
        .collect();
    match (over_point.into_inner(), over_total.into_inner()) {
        (usize::MAX, false) => Ok(with_active(AnswerPairings::Wire(pairings), active.ids())),
        (usize::MAX, true) => Err(Overflow::Total),
        (point, _) => Err(Overflow::Point(point)),
    }
}

pub(super) fn nearest(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    scan: &DecodedScan,
    pose: &Pose,
) -> Result<Answer, Rejection> {
    let k = request.k;
    if !(1..=MAX_K).contains(&k) {
        return Err(bad(format!("k = {k} must be within 1..={MAX_K}")));
    }
    let keyframes = request.keyframes;
    if keyframes > MAX_KEYFRAMES {
        return Err(bad(format!(
            "keyframes = {keyframes} must be within 0 (the active set) ..={MAX_KEYFRAMES}"
        )));
    }
    let r = request.radius;
    if !(r.is_finite() && (0.0..=MAX_RADIUS).contains(&r)) {
        return Err(bad(format!(
            "radius {r} m of a nearest request must be 0 (any distance) or within (0, {MAX_RADIUS}]"
        )));
    }
    let active = match keyframes {
        0 => activate(map, session, pose, Activation::of_map(map, false))?,
        n => {
            let ids = map.map.surroundings(pose, n as usize);
            activate_ids(map, session, ids, false)?
        }
    };
    // Never over: the admission checked points x k against max-answer-bytes.
    let caps = Caps {
        per_point: usize::MAX,
        total: usize::MAX,
    };
    let bound_sq = if r > 0.0 { r * r } else { f32::INFINITY };
    let answer = search_each(&active, scan, pose, caps, |active, p| {
        active.nearest_k_within(p, k as usize, bound_sq)
    });
    Ok(answer.expect("k-nearest answers have no caps"))
}

pub(super) fn radius(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    scan: &DecodedScan,
    pose: &Pose,
    limits: &Limits,
) -> Result<Answer, Rejection> {
    let r = request.radius;
    if !(r.is_finite() && r > 0.0 && r <= MAX_RADIUS) {
        return Err(bad(format!(
            "radius {r} m must be within (0, {MAX_RADIUS}]"
        )));
    }
    let caps = Caps {
        per_point: limits.max_radius_points,
        total: (limits.max_answer_bytes / PAIRING_BYTES) as usize,
    };
    let active = activate(map, session, pose, Activation::of_map(map, false))?;
    let answer = search_each(&active, scan, pose, caps, |active, p| {
        active.within_radius(p, r as f64)
    });
    answer.map_err(|overflow| match overflow {
        Overflow::Point(point) => Rejection {
            status: StatusCode::TooLarge,
            message: format!(
                "scan point {point} has more than {} map points within {r} m, over max-radius-points (server.toml); use a smaller radius",
                caps.per_point
            ),
            detail: point as u64,
        },
        Overflow::Total => Rejection::new(
            StatusCode::TooLarge,
            format!(
                "the radius answer grew past {} pairings ({} MiB), over max-answer-bytes (server.toml); use a smaller radius or fewer points",
                caps.total,
                limits.max_answer_bytes >> 20
            ),
        ),
    })
}

/// Cov2cov pairings at `pose` and the active keyframes used.
pub(super) fn cov2cov(
    map: &ServedMap,
    session: &mut Session,
    cloud: &PointCloud,
    covariances: &[[f32; 6]],
    pose: &Pose,
    max_pair_dist: f32,
    activation: Activation,
) -> Result<(Vec<Pairing>, Vec<u64>), Rejection> {
    if !(max_pair_dist.is_finite() && max_pair_dist > 0.0 && max_pair_dist <= MAX_PAIR_DIST) {
        return Err(bad(format!(
            "max_pair_dist {max_pair_dist} m must be within (0, {MAX_PAIR_DIST}]"
        )));
    }
    let active = activate(map, session, pose, activation)?;
    // Exact mode searches its merged tree once per point: nothing to remember.
    let memo = match active.merged() {
        None => session.memos.for_points(cloud.len()),
        Some(_) => None,
    };
    let pairings = active
        .cov2cov_remembering(cloud, pose, max_pair_dist as f64, Some(covariances), memo)
        .map_err(map_error)?;
    Ok((pairings, active.ids().to_vec()))
}
