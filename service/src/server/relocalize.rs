//! `Relocalize`: where a scan was taken, with no pose guess. The search runs on the
//! map's baked place grid; each proposed place is verified by the same registrations
//! as `Localize`, against the served map in the client's session.

use kfmap_protocol::{
    DecodedScan, FLAG_LEVELLED, Rejection, RequestHeader, StatusCode, pose_to_wire,
};
use kfmap_shared::geometry::Pose;
use kfmap_shared::place::{RelocalizeStatus, propose, verify};
use kfmap_shared::tracking::{covariance_to_wire, pose_covariance};
use nalgebra::Vector3;

use super::answer::{Answer, AnswerPairings, bad, exact_mode, with_active};
use super::limits::Limits;
use super::localize::localize_params;
use super::register::{MapRegistration, coarse_error, prepare, register_approximate};
use super::session::Session;
use super::state::ServedMap;

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
    let proposal =
        propose(&grid, scan.points, map_up, &params).map_err(|e| bad(format!("scan: {e}")))?;
    let searched = started.elapsed();
    let mut stages = prepare(scan, limits);
    let mut against = MapRegistration {
        map,
        session,
        exact,
        active: Vec::new(),
    };
    // The candidates' coarse registrations run in parallel, so they share a coarse
    // scan of their own; the ladder's stages build theirs on first use.
    let mut candidates = prepare(scan, limits);
    let (coarse_cloud, coarse_covs) = candidates.coarse().map_err(coarse_error)?;
    let found = verify(
        &proposal,
        fine,
        &limits.tracking,
        &params,
        |start, stage| register_approximate(map, coarse_cloud, coarse_covs, start, stage),
        |start, stage| {
            let (cloud, covs) = stages.for_stage(stage).map_err(coarse_error)?;
            against.register(cloud, covs, start, stage)
        },
    )?;
    tracing::debug!(
        "relocalize: search {:.1} ms ({} points, {} nodes{}), verify {:.1} ms ({} registrations): {}",
        searched.as_secs_f64() * 1e3,
        proposal.points,
        proposal.nodes,
        if proposal.exhausted {
            ", stopped at max-lookups"
        } else {
            ""
        },
        (started.elapsed() - searched).as_secs_f64() * 1e3,
        found.registrations,
        found.status.name()
    );
    let mut answer = with_active(AnswerPairings::default(), &against.active);
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
    Ok(answer)
}
