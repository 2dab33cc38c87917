//! What the server answers to one request: pure computation on the shared map and the
//! client's session, no transport. The same function serves the IPC loop and the
//! in-process tests that check the IPC answers bit for bit.

use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;

use kfmap_protocol::{
    Cov2CovMode, DecodedScan, Rejection, RequestHeader, RequestKind, ResponseHeader, StatusCode,
    WirePairing, check_version, correspondences_from_pairings, decode_imu, decode_scan,
    decode_stamp, localize_stage, pose_from_wire, pose_to_wire,
};
use kfmap_shared::cloud::PointCloud;
use kfmap_shared::cov::{CovOptions, estimate_covariances};
use kfmap_shared::geometry::{Pose, to_point, transform_point};
use kfmap_shared::gravity::ImuWindow;
use kfmap_shared::map::{ActiveSet, MapError, MapHit, Pairing};
use kfmap_shared::place::RelocalizeParams;
use kfmap_shared::registration::{RegistrationError, RegistrationResult, solve_pose};
use kfmap_shared::tracking::{
    Expectation, Stage, TrackingParams, TrackingStatus, covariance_to_wire, localize_scan,
};
use rayon::prelude::*;

use super::relocalize::relocalize;
use super::session::Session;
use super::state::ServedMap;
use crate::config::ServerConfig;

/// Largest `k` of a `Nearest` request.
pub const MAX_K: u32 = 64;
/// Bytes of one answer pairing.
pub const PAIRING_BYTES: u64 = std::mem::size_of::<WirePairing>() as u64;
/// Largest radius of a `Radius` request, metres.
pub const MAX_RADIUS: f32 = 20.0;
/// Largest pairing distance of `Cov2Cov` / `Localize`, metres.
pub const MAX_PAIR_DIST: f32 = 50.0;
/// Most iterations of a `Localize` request.
pub const MAX_ITERATIONS: u32 = 100;
/// Largest `max_correction` of a `Localize` request, metres.
pub const MAX_CORRECTION: f32 = 1000.0;

/// Request limits from `server.toml`.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Points per scan, at most.
    pub max_points: usize,
    /// Map points one `Radius` query point may find, at most.
    pub max_radius_points: usize,
    /// Bytes of pairings one answer may hold.
    pub max_answer_bytes: u64,
    /// Covariances estimated for scans sent without them.
    pub scan_covariance: CovOptions,
    /// Checks and retry ladder of `Localize`.
    pub tracking: TrackingParams,
    /// Search and verdict of `Relocalize`.
    pub relocalize: RelocalizeParams,
    /// What `Cov2CovMode::MapDefault` requests get (`server.toml`); `MapDefault` here
    /// means the map's own choice (`bake.toml`).
    pub cov2cov_mode: Cov2CovMode,
}

impl Limits {
    /// The limits `server.toml` sets.
    pub fn of(config: &ServerConfig) -> Self {
        Self {
            max_points: config.server.max_points_per_request,
            max_radius_points: config.server.max_radius_points as usize,
            max_answer_bytes: config.server.max_answer_bytes,
            scan_covariance: config.covariance,
            tracking: config.tracking,
            relocalize: config.relocalize,
            cov2cov_mode: config.server.cov2cov_mode,
        }
    }
}

impl Default for Limits {
    /// The shipped `server.toml`'s.
    fn default() -> Self {
        Self::of(&ServerConfig::default())
    }
}

/// A response: header and pairings.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// Status, timings, pose, gravity.
    pub header: ResponseHeader,
    /// Map points found.
    pub pairings: AnswerPairings,
}

/// The pairings of an answer. Cov2cov pairings stay as the map returns them until they
/// are written out, so the server converts them straight into shared memory.
#[derive(Debug, Clone, PartialEq)]
pub enum AnswerPairings {
    /// Already in the wire layout (nearest, radius).
    Wire(Vec<WirePairing>),
    /// Cov2cov pairings from the map.
    Cov2Cov(Vec<Pairing>),
}

impl Default for AnswerPairings {
    fn default() -> Self {
        Self::Wire(Vec::new())
    }
}

impl AnswerPairings {
    /// Number of pairings.
    pub fn len(&self) -> usize {
        match self {
            Self::Wire(v) => v.len(),
            Self::Cov2Cov(v) => v.len(),
        }
    }

    /// True without pairings.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Writes every pairing, in the wire layout, into `out` (exactly [`Self::len`] long).
    pub fn write(&self, out: &mut [MaybeUninit<WirePairing>]) {
        assert_eq!(
            out.len(),
            self.len(),
            "the response was loaned for another count"
        );
        match self {
            Self::Wire(v) => out.par_iter_mut().zip(v.par_iter()).for_each(|(slot, p)| {
                slot.write(*p);
            }),
            Self::Cov2Cov(v) => out.par_iter_mut().zip(v.par_iter()).for_each(|(slot, p)| {
                slot.write(WirePairing::from(p));
            }),
        }
    }

    /// The pairings in the wire layout.
    pub fn into_wire(self) -> Vec<WirePairing> {
        match self {
            Self::Wire(v) => v,
            Self::Cov2Cov(v) => v.par_iter().map(WirePairing::from).collect(),
        }
    }
}

impl Answer {
    /// An error answer.
    pub fn rejected(request_id: u64, rejection: &Rejection) -> Self {
        let mut header = ResponseHeader {
            request_id,
            status: rejection.status as u32,
            detail: rejection.detail,
            ..Default::default()
        };
        header.set_message(&rejection.message);
        Self {
            header,
            pairings: AnswerPairings::default(),
        }
    }
}

/// Answers one request on `map` within the client's `session`. Status requests are
/// answered by the caller (they need the server's counters).
pub fn answer(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    payload: &[f32],
    limits: &Limits,
) -> Answer {
    let started = Instant::now();
    let mut answer = match compute(map, session, request, payload, limits) {
        Ok(answer) => answer,
        Err(rejection) => Answer::rejected(request.request_id, &rejection),
    };
    answer.header.request_id = request.request_id;
    answer.header.server_us = started.elapsed().as_secs_f64() * 1e6;
    answer
}

pub(super) fn bad(message: impl Into<String>) -> Rejection {
    Rejection::new(StatusCode::BadRequest, message)
}

fn compute(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    payload: &[f32],
    limits: &Limits,
) -> Result<Answer, Rejection> {
    check_version(request)?;
    let kind = RequestKind::from_code(request.kind).ok_or_else(|| Rejection {
        status: StatusCode::UnknownKind,
        message: format!("request kind {} is not known to this server", request.kind),
        detail: request.kind as u64,
    })?;
    let pose = pose_from_wire(&request.pose).ok_or_else(|| {
        bad("the pose guess is not finite or its quaternion is not of unit length")
    })?;
    session.follow(map.generation);
    match kind {
        RequestKind::Echo => echo(request, payload, limits),
        RequestKind::ImuWindow => imu_window(session, request, payload, &pose),
        RequestKind::Status | RequestKind::Reload => Err(Rejection::new(
            StatusCode::Internal,
            "status and reload requests are answered by the server loop",
        )),
        _ => {
            let scan = decode_scan(request, payload, limits.max_points)?;
            match kind {
                RequestKind::Nearest => nearest(map, session, request, &scan, &pose),
                RequestKind::Radius => radius(map, session, request, &scan, &pose, limits),
                RequestKind::Cov2Cov => {
                    let exact = exact_mode(map, request.mode, limits)?;
                    let covs = scan_covariances(&scan, limits);
                    let (pairings, active) = cov2cov(
                        map,
                        session,
                        &scan_cloud(&scan),
                        &covs,
                        &pose,
                        request.max_pair_dist,
                        exact,
                    )?;
                    Ok(with_active(AnswerPairings::Cov2Cov(pairings), &active))
                }
                RequestKind::Relocalize => relocalize(map, session, request, &scan, &pose, limits),
                _ => localize(map, session, request, &scan, &pose, limits),
            }
        }
    }
}

/// A no-work answer: the header only, `detail` = points received (round trips).
fn echo(request: &RequestHeader, payload: &[f32], limits: &Limits) -> Result<Answer, Rejection> {
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

pub(super) fn with_active(pairings: AnswerPairings, active: &[u64]) -> Answer {
    let mut header = ResponseHeader::default();
    let used = active.len().min(header.active.len());
    header.active[..used].copy_from_slice(&active[..used]);
    header.active_len = used as u32;
    Answer { header, pairings }
}

fn map_error(e: MapError) -> Rejection {
    Rejection::new(StatusCode::Internal, format!("map: {e}"))
}

/// True when a request of wire mode `mode` is answered in exact mode: its own mode,
/// else the server's (`server.toml`), else the map's (`bake.toml`).
pub(super) fn exact_mode(map: &ServedMap, mode: u32, limits: &Limits) -> Result<bool, Rejection> {
    let requested = Cov2CovMode::from_code(mode).ok_or_else(|| {
        bad(format!(
            "cov2cov mode {mode} is unknown (0 map default, 1 approximate, 2 exact)"
        ))
    })?;
    Ok(matches!(
        (requested, limits.cov2cov_mode, map.exact_by_default),
        (Cov2CovMode::Exact, _, _)
            | (Cov2CovMode::MapDefault, Cov2CovMode::Exact, _)
            | (Cov2CovMode::MapDefault, Cov2CovMode::MapDefault, true)
    ))
}

/// The active set for a query at `pose`, with the session's merged-submap cache.
fn activate<'m>(
    map: &'m ServedMap,
    session: &mut Session,
    pose: &Pose,
    exact: bool,
) -> Result<ActiveSet<'m>, Rejection> {
    let ids = map.map.select(pose);
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

/// Every scan point moved by `pose` and searched by `search` in the active set: the
/// hits as pairings without information, in query order. The search stops once a
/// point finds more than `caps.per_point` or the answer more than `caps.total`, so the
/// answer never outgrows them.
fn search_each(
    map: &ServedMap,
    session: &mut Session,
    scan: &DecodedScan,
    pose: &Pose,
    caps: Caps,
    search: impl Fn(&ActiveSet, &[f32; 3]) -> Vec<MapHit> + Sync,
) -> Result<Result<Answer, Overflow>, Rejection> {
    let active = activate(map, session, pose, false)?;
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
                search(&active, &to_map_frame(pose, p))
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
    Ok(match (over_point.into_inner(), over_total.into_inner()) {
        (usize::MAX, false) => Ok(with_active(AnswerPairings::Wire(pairings), active.ids())),
        (usize::MAX, true) => Err(Overflow::Total),
        (point, _) => Err(Overflow::Point(point)),
    })
}

fn nearest(
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
    // Never over: the admission checked points x k against max-answer-bytes.
    let caps = Caps {
        per_point: usize::MAX,
        total: usize::MAX,
    };
    let answer = search_each(map, session, scan, pose, caps, |active, p| {
        active.nearest_k(p, k as usize)
    })?;
    Ok(answer.expect("k-nearest answers have no caps"))
}

fn radius(
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
    let answer = search_each(map, session, scan, pose, caps, |active, p| {
        active.within_radius(p, r as f64)
    })?;
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

/// The scan's covariances: the client's, or estimated with the server's options.
fn scan_covariances(scan: &DecodedScan, limits: &Limits) -> Vec<[f32; 6]> {
    match scan.covariances {
        Some(c) => c.to_vec(),
        None => estimate_covariances(scan.points, &limits.scan_covariance).values,
    }
}

/// The scan as the map takes it, built once per request (`Localize` iterates on it).
fn scan_cloud(scan: &DecodedScan) -> PointCloud {
    PointCloud {
        points: scan.points.to_vec(),
        view_dirs: scan.view_dirs.map(<[_]>::to_vec),
        intensity: None,
        time: None,
    }
}

/// Cov2cov pairings at `pose` and the active keyframes used.
fn cov2cov(
    map: &ServedMap,
    session: &mut Session,
    cloud: &PointCloud,
    covariances: &[[f32; 6]],
    pose: &Pose,
    max_pair_dist: f32,
    exact: bool,
) -> Result<(Vec<Pairing>, Vec<u64>), Rejection> {
    if !(max_pair_dist.is_finite() && max_pair_dist > 0.0 && max_pair_dist <= MAX_PAIR_DIST) {
        return Err(bad(format!(
            "max_pair_dist {max_pair_dist} m must be within (0, {MAX_PAIR_DIST}]"
        )));
    }
    let active = activate(map, session, pose, exact)?;
    let pairings = active
        .cov2cov(cloud, pose, max_pair_dist as f64, Some(covariances))
        .map_err(map_error)?;
    Ok((pairings, active.ids().to_vec()))
}

/// The fine stage and the client's expectation of a `Localize` request.
pub fn localize_params(request: &RequestHeader) -> Result<(Stage, Expectation), Rejection> {
    let (d, n, c, e) = (
        request.max_pair_dist,
        request.max_iterations,
        request.max_correction,
        request.expected_inlier_ratio,
    );
    if !(d.is_finite() && d > 0.0 && d <= MAX_PAIR_DIST) {
        return Err(bad(format!(
            "max_pair_dist {d} m must be within (0, {MAX_PAIR_DIST}]"
        )));
    }
    if !(1..=MAX_ITERATIONS).contains(&n) {
        return Err(bad(format!(
            "max_iterations {n} must be within 1..={MAX_ITERATIONS}"
        )));
    }
    if !(c.is_finite() && (0.0..=MAX_CORRECTION).contains(&c)) {
        return Err(bad(format!(
            "max_correction {c} m must be within [0, {MAX_CORRECTION}] (0: no bound)"
        )));
    }
    if !(0.0..=1.0).contains(&e) {
        return Err(bad(format!(
            "expected_inlier_ratio {e} must be within [0, 1] (0: unknown)"
        )));
    }
    let expected = Expectation {
        max_correction: (c > 0.0).then_some(c as f64),
        inlier_ratio: (e > 0.0).then_some(e as f64),
    };
    Ok((localize_stage(d, n), expected))
}

/// Server-side localization: the same checks and retry ladder a client runs over
/// cov2cov answers ([`localize_scan`]), each registration the shared GICP loop.
fn localize(
    map: &ServedMap,
    session: &mut Session,
    request: &RequestHeader,
    scan: &DecodedScan,
    pose: &Pose,
    limits: &Limits,
) -> Result<Answer, Rejection> {
    let (fine, expected) = localize_params(request)?;
    let exact = exact_mode(map, request.mode, limits)?;
    // Checked before the work: a bad stamp must not throw away a solved pose.
    let stamp = decode_stamp(request)?;
    let mut stages = ScanStages::new(scan, limits);
    let mut against = MapRegistration {
        map,
        session,
        exact,
        active: Vec::new(),
    };
    let found = localize_scan(pose, &expected, fine, &limits.tracking, |start, stage| {
        let (cloud, covs) = stages.for_stage(stage)?;
        against.register(cloud, covs, start, stage)
    })?;
    let active = against.active;
    // An adopted pose with its scan's time joins the session's motion for gravity.
    if let Some(stamp) = stamp
        && found.health.status != TrackingStatus::Lost
    {
        session.gravity.add_pose(stamp, found.pose);
    }
    let mut answer = with_active(AnswerPairings::default(), &active);
    let (h, health) = (&mut answer.header, &found.health);
    h.pose = pose_to_wire(&found.pose);
    h.covariance = covariance_to_wire(health.covariance.as_ref());
    h.fitness = [health.inlier_ratio, health.rmse];
    h.iterations = health.iterations;
    h.converged = health.converged as u32;
    h.tracking = health.status as u32;
    h.reasons = health.reasons.0;
    h.registrations = health.registrations;
    h.degenerate = health.degenerate as u32;
    h.constraint = [
        health.constraint.rotation_ratio,
        health.constraint.translation_ratio,
    ];
    h.pose_correction = health.correction;
    Ok(answer)
}

/// A scan as registrations take it: as sent, and coarse (built on the first coarse
/// registration, then reused), each with its covariances.
pub(super) struct ScanStages<'s> {
    scan: &'s DecodedScan<'s>,
    limits: &'s Limits,
    fine: Option<(PointCloud, Vec<[f32; 6]>)>,
    coarse: Option<(PointCloud, Vec<[f32; 6]>)>,
}

impl<'s> ScanStages<'s> {
    pub(super) fn new(scan: &'s DecodedScan<'s>, limits: &'s Limits) -> Self {
        Self {
            scan,
            limits,
            fine: None,
            coarse: None,
        }
    }

    /// The cloud and covariances `stage` registers (each built on first use).
    pub(super) fn for_stage(
        &mut self,
        stage: &Stage,
    ) -> Result<(&PointCloud, &[[f32; 6]]), Rejection> {
        if !stage.coarse {
            let (cloud, covs) = self.fine.get_or_insert_with(|| {
                (
                    scan_cloud(self.scan),
                    scan_covariances(self.scan, self.limits),
                )
            });
            return Ok((cloud, covs.as_slice()));
        }
        if self.coarse.is_none() {
            self.coarse = Some(coarse_scan(self.scan, self.limits)?);
        }
        let (c, v) = self.coarse.as_ref().expect("built above");
        Ok((c, v.as_slice()))
    }
}

/// The coarse scan ([`TrackingParams::coarse_scan`]) with its covariances.
pub(super) fn coarse_scan(
    scan: &DecodedScan,
    limits: &Limits,
) -> Result<(PointCloud, Vec<[f32; 6]>), Rejection> {
    let c = limits
        .tracking
        .coarse_scan(scan.points, scan.view_dirs)
        .map_err(|e| bad(format!("coarse scan: {e}")))?;
    let covs = estimate_covariances(&c.points, &limits.scan_covariance).values;
    Ok((c, covs))
}

/// Registrations against the served map in one client's session.
pub(super) struct MapRegistration<'a> {
    pub(super) map: &'a ServedMap,
    pub(super) session: &'a mut Session,
    pub(super) exact: bool,
    /// Keyframes of the last pairing.
    pub(super) active: Vec<u64>,
}

impl MapRegistration<'_> {
    /// One registration of `cloud` (with its covariances) from `start` over the map's
    /// cov2cov pairings; `None` when no scan point has a pair.
    pub(super) fn register(
        &mut self,
        cloud: &PointCloud,
        covs: &[[f32; 6]],
        start: &Pose,
        stage: &Stage,
    ) -> Result<Option<RegistrationResult>, Rejection> {
        register_over(cloud, start, stage, |at| {
            let (pairings, ids) = cov2cov(
                self.map,
                self.session,
                cloud,
                covs,
                at,
                stage.max_pair_dist as f32,
                self.exact,
            )?;
            self.active = ids;
            Ok(pairings)
        })
    }
}

/// As [`MapRegistration::register`] in approximate mode and outside any session (no
/// merged-submap cache to share), so registrations may run on several threads.
pub(super) fn register_approximate(
    map: &ServedMap,
    cloud: &PointCloud,
    covs: &[[f32; 6]],
    start: &Pose,
    stage: &Stage,
) -> Result<Option<RegistrationResult>, Rejection> {
    register_over(cloud, start, stage, |at| {
        let ids = map.map.select(at);
        let active = map
            .map
            .activate_cached(ids, &mut None, false)
            .map_err(map_error)?;
        active
            .cov2cov(cloud, at, stage.max_pair_dist, Some(covs))
            .map_err(map_error)
    })
}

/// The registration loop over `pairings_at(pose)`; `None` when no scan point has a pair.
fn register_over(
    cloud: &PointCloud,
    start: &Pose,
    stage: &Stage,
    mut pairings_at: impl FnMut(&Pose) -> Result<Vec<Pairing>, Rejection>,
) -> Result<Option<RegistrationResult>, Rejection> {
    let result = solve_pose(start, &stage.params(), cloud.len(), |at| {
        let pairings = pairings_at(at).map_err(LocalizeError::Rejected)?;
        Ok::<_, LocalizeError>(correspondences_from_pairings(&pairings, &cloud.points))
    });
    match result {
        Ok(r) => Ok(Some(r)),
        Err(LocalizeError::Registration(RegistrationError::NoCorrespondences { .. })) => Ok(None),
        Err(LocalizeError::Registration(e)) => Err(bad(format!("localization: {e}"))),
        Err(LocalizeError::Rejected(r)) => Err(r),
    }
}

enum LocalizeError {
    Rejected(Rejection),
    Registration(RegistrationError),
}

impl From<RegistrationError> for LocalizeError {
    fn from(e: RegistrationError) -> Self {
        Self::Registration(e)
    }
}

fn imu_window(
    session: &mut Session,
    request: &RequestHeader,
    payload: &[f32],
    pose: &Pose,
) -> Result<Answer, Rejection> {
    const MAX_IMU_SAMPLES: usize = 1 << 16;
    let samples = decode_imu(request, payload, MAX_IMU_SAMPLES)?;
    let stamp = decode_stamp(request)?;
    let id = request.keyframe_or_scan_id;
    session
        .gravity
        .add_window(id, ImuWindow::new(samples), *pose, stamp);
    let mut answer = with_active(AnswerPairings::default(), &[]);
    let h = &mut answer.header;
    let pool = session.gravity.answer();
    h.gravity_members = pool.members as u32;
    h.gravity_compensated = pool.compensated as u32;
    h.gravity_pending = pool.pending as u32;
    h.gravity_skipped = pool.skipped as u32;
    if let Some(c) = pool.correction {
        let q = nalgebra::UnitQuaternion::from_rotation_matrix(&c.rotation);
        let (health, bias) = (&c.estimate.health, &c.estimate.accel_bias);
        h.has_gravity = 1;
        h.gravity = c.estimate.g.into();
        h.roll_pitch = [c.roll, c.pitch];
        h.correction = [q.i, q.j, q.k, q.w];
        h.gravity_inliers = health.inliers as u32;
        h.gravity_spread_deg = health.spread_deg;
        h.accel_bias = bias.mps2.into();
        h.accel_bias_sigma = bias.sigma_mps2.map_or([0.0; 3], Into::into);
        h.bias_observable = bias.observable as u32;
    }
    Ok(answer)
}
