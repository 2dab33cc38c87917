//! `Localize`: server-side localization of one scan from a pose guess, with the same
//! checks and retry ladder a client runs over cov2cov answers.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::tracking::{Expectation, Stage, TrackingStatus, localize_scan};
use kfmap_protocol::{
    DecodedScan, Rejection, RequestHeader, decode_stamp, localize_stage, write_localized,
};

use super::answer::{Answer, AnswerPairings, bad, exact_mode, with_active};
use super::limits::{Limits, MAX_CORRECTION, MAX_ITERATIONS, MAX_PAIR_DIST};
use super::queries::Activation;
use super::register::{MapRegistration, coarse_error, prepare};
use super::session::Session;
use super::state::ServedMap;

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
pub(super) fn localize(
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
    let mut stages = prepare(scan, limits);
    let mut against = MapRegistration {
        map,
        session,
        activation: Activation::of_map(map, exact),
        active: Vec::new(),
    };
    let found = localize_scan(pose, &expected, fine, &limits.tracking, |start, stage| {
        let (cloud, covs) = stages.for_stage(stage).map_err(coarse_error)?;
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
    write_localized(&mut answer.header, &found.pose, &found.health);
    Ok(answer)
}
