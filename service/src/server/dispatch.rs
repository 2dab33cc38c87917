//! What the server answers to one request: pure computation on the shared map and the
//! client's session, no transport. The same function serves the IPC loop and the
//! in-process tests that check the IPC answers bit for bit.

use std::time::Instant;

use kfmap_protocol::{
    Rejection, RequestHeader, RequestKind, StatusCode, check_version, decode_scan, pose_from_wire,
};

use super::answer::{Answer, AnswerPairings, bad, exact_mode, with_active};
use super::imu::imu_window;
use super::limits::Limits;
use super::localize::localize;
use super::queries::{Activation, cov2cov, echo, nearest, radius};
use super::register::prepare;
use super::relocalize::relocalize;
use super::session::Session;
use super::state::ServedMap;

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
        RequestKind::Status | RequestKind::Reload | RequestKind::Track | RequestKind::TrackImu => {
            Err(Rejection::new(
                StatusCode::Internal,
                "status, reload and track requests are answered by the server loop",
            ))
        }
        _ => {
            let scan = decode_scan(request, payload, limits.max_points)?;
            match kind {
                RequestKind::Nearest => nearest(map, session, request, &scan, &pose),
                RequestKind::Radius => radius(map, session, request, &scan, &pose, limits),
                RequestKind::Cov2Cov => {
                    let exact = exact_mode(map, request.mode, limits)?;
                    let mut prepared = prepare(&scan, limits);
                    let (cloud, covs) = prepared.fine();
                    let (pairings, active) = cov2cov(
                        map,
                        session,
                        cloud,
                        covs,
                        &pose,
                        request.max_pair_dist,
                        Activation::of_map(map, exact),
                    )?;
                    Ok(with_active(AnswerPairings::Cov2Cov(pairings), &active))
                }
                RequestKind::Relocalize => relocalize(map, session, request, &scan, &pose, limits),
                _ => localize(map, session, request, &scan, &pose, limits),
            }
        }
    }
}
