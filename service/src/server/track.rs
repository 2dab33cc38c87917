//! `Track` and `TrackImu`: a tracker hosted for the session (docs/DESIGN.md#hosted-tracking).
//! The server runs the same [`Tracker`] as `kfmap localize` and the ROS 2 node on each
//! scan a client sends; the tracker's own requests (localize, relocalize, nearest) are
//! answered on this thread within the client's session, without a round trip.

use std::sync::{Arc, Mutex};

use kfmap_client::hosted::tracked_to_wire;
use kfmap_client::{Client, ClientError, Dispatch, LocalizeOptions, Tracker, TrackerOptions};
use kfmap_geometry::motion::GyroParams;
use kfmap_protocol::{
    Cov2CovMode, FLAG_TRACK_FROM_POSE, FLAG_TRACK_RESET, Rejection, RequestHeader, RequestKind,
    ResponseHeader, ScanPayload, StatusCode, WirePairing, WireTrack, decode_imu, decode_scan,
    decode_stamp, pose_from_wire,
};

use super::answer::{Answer, AnswerPairings, bad};
use super::dispatch;
use super::limits::Limits;
use super::localize::localize_params;
use super::session::{HostedTracker, Session};
use super::state::ServedMap;

/// IMU samples one `TrackImu` request carries at most (as an `ImuWindow`).
const MAX_IMU_SAMPLES: usize = 1 << 16;
/// Seconds of IMU log a hosted tracker keeps before its newest sample (as the ROS 2
/// node's `[imu] keep-s`): a lost stretch longer than this is predicted without it.
const IMU_KEEP_S: f64 = 20.0;

/// Answers a hosted tracker's own requests in this process, within its client's
/// session, as the IPC loop would.
struct Loopback {
    map: Arc<ServedMap>,
    session: Arc<Mutex<Session>>,
    limits: Limits,
}

impl Dispatch for Loopback {
    fn answer(
        &mut self,
        header: &RequestHeader,
        payload: &[f32],
    ) -> (ResponseHeader, Vec<WirePairing>) {
        let mut session = self.session.lock().unwrap_or_else(|e| e.into_inner());
        let answer = match RequestKind::from_code(header.kind) {
            // What the tracker asks for; status and reload are the server loop's.
            Some(
                RequestKind::Localize
                | RequestKind::Relocalize
                | RequestKind::Nearest
                | RequestKind::Cov2Cov,
            ) => dispatch::answer(&self.map, &mut session, header, payload, &self.limits),
            _ => Answer::rejected(
                header.request_id,
                &Rejection::new(
                    StatusCode::Internal,
                    format!("a hosted tracker asked for request kind {}", header.kind),
                ),
            ),
        };
        (answer.header, answer.pairings.into_wire())
    }
}

/// Answers a `Track` or `TrackImu` request of `client_node`'s session.
pub fn answer(
    map: Arc<ServedMap>,
    session: Arc<Mutex<Session>>,
    request: &RequestHeader,
    payload: &[f32],
    limits: &Limits,
) -> Answer {
    let started = std::time::Instant::now();
    let hosted = session
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .hosted
        .clone();
    // Held for the whole request: one client's scans are tracked one at a time.
    let mut hosted = hosted.lock().unwrap_or_else(|e| e.into_inner());
    let computed = match RequestKind::from_code(request.kind) {
        Some(RequestKind::TrackImu) => push_imu(&mut hosted, request, payload),
        _ => {
            let mut client = Client::in_process(
                &map.path.display().to_string(),
                request.client_node,
                Box::new(Loopback {
                    map: map.clone(),
                    session,
                    limits: *limits,
                }),
            );
            track(&mut hosted, &mut client, request, payload, limits)
        }
    };
    let mut answer = computed.unwrap_or_else(|rejection| Answer::rejected(0, &rejection));
    answer.header.request_id = request.request_id;
    answer.header.server_us = started.elapsed().as_secs_f64() * 1e6;
    answer
}

/// `Track`: the scan through the session's tracker, started anew when asked.
fn track(
    hosted: &mut HostedTracker,
    client: &mut Client,
    request: &RequestHeader,
    payload: &[f32],
    limits: &Limits,
) -> Result<Answer, Rejection> {
    let scan = decode_scan(request, payload, limits.max_points)?;
    let t = decode_stamp(request)?
        .ok_or_else(|| bad("a Track request needs the scan's time in `stamp` (FLAG_STAMPED)"))?;
    let reset = request.flags & FLAG_TRACK_RESET != 0;
    if reset || !hosted.started_by_scan {
        // The same bounds as `Localize` (its correction fields are checked, not used).
        localize_params(request)?;
        let mode = Cov2CovMode::from_code(request.mode)
            .ok_or_else(|| bad(format!("cov2cov mode {} is unknown", request.mode)))?;
        let options = TrackerOptions {
            localize: LocalizeOptions {
                max_iterations: request.max_iterations,
                max_pair_dist: request.max_pair_dist,
                mode,
                tracking: limits.tracking,
                ..LocalizeOptions::default()
            },
            server_side: true,
            ..TrackerOptions::default()
        };
        let start = if reset && request.flags & FLAG_TRACK_FROM_POSE != 0 {
            Some(pose_from_wire(&request.pose).ok_or_else(|| {
                bad("the start pose is not finite or its quaternion is not of unit length")
            })?)
        } else {
            None
        };
        let mut tracker = match start {
            Some(pose) => Tracker::new(pose, options),
            None => Tracker::relocalizing(options),
        };
        if let Some(gyro) = hosted.tracker.as_ref().and_then(Tracker::gyro) {
            tracker = tracker.with_gyro(gyro.clone());
        }
        hosted.tracker = Some(tracker);
        hosted.started_by_scan = true;
    }
    let tracker = hosted.tracker.as_mut().expect("started above");
    let scan = ScanPayload {
        points: scan.points,
        view_dirs: scan.view_dirs,
        covariances: scan.covariances,
    };
    let tracked = tracker.track(client, &scan, t).map_err(rejection_of)?;
    let mut header = ResponseHeader::default();
    let places = tracked_to_wire(&tracked, &mut header);
    Ok(Answer {
        header,
        pairings: AnswerPairings::Wire(places),
    })
}

/// `TrackImu`: samples for the tracker's gyro (a tracker is made for them when the
/// session has none yet). The request's pose rotation is `R_lidar_imu`.
fn push_imu(
    hosted: &mut HostedTracker,
    request: &RequestHeader,
    payload: &[f32],
) -> Result<Answer, Rejection> {
    let samples = decode_imu(request, payload, MAX_IMU_SAMPLES)?;
    let mounting = pose_from_wire(&request.pose)
        .ok_or_else(|| bad("the IMU mounting (pose rotation) is not a unit quaternion"))?;
    let tracker = hosted
        .tracker
        .get_or_insert_with(|| Tracker::relocalizing(TrackerOptions::default()));
    let params = match tracker.gyro() {
        Some(gyro) => *gyro.params(),
        None => {
            let (r, p, y) = mounting.rotation.euler_angles();
            GyroParams {
                lidar_from_imu_rpy_deg: [r, p, y].map(f64::to_degrees),
                ..GyroParams::default()
            }
        }
    };
    let refused = tracker
        .push_imu(&samples, params, IMU_KEEP_S)
        .map_err(|e| bad(format!("IMU samples: {e}")))?;
    let header = ResponseHeader {
        track: WireTrack {
            imu_refused: refused as u32,
            ..WireTrack::default()
        },
        ..ResponseHeader::default()
    };
    Ok(Answer {
        header,
        pairings: AnswerPairings::default(),
    })
}

/// The rejection a tracker's failure becomes: a refusal of its own requests keeps its
/// status and message.
fn rejection_of(e: ClientError) -> Rejection {
    match e {
        ClientError::Rejected {
            status,
            message,
            detail,
        } => Rejection {
            status,
            message,
            detail,
        },
        ClientError::Invalid(message) => bad(message),
        other => Rejection::new(StatusCode::Internal, format!("hosted tracker: {other}")),
    }
}
