//! Tracking hosted by the server (`Track`, `TrackImu`; docs/DESIGN.md#hosted-tracking):
//! the server keeps one [`Tracker`](crate::Tracker) per session and runs it on each
//! scan the client sends, so a client that cannot run the tracker itself (Python, a
//! thin process) gets the same poses, statuses, hypotheses and trust figures as
//! `kfmap localize`. This module is both sides of the wire: the requests a client
//! sends and the answer a server writes.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::ImuSample;
use kfmap_protocol::{
    FLAG_TRACK_FROM_POSE, FLAG_TRACK_RESET, RequestHeader, RequestKind, ResponseHeader,
    ScanPayload, TRACK_EXPLAINED, TRACK_MAX_CORRECTION, TRACK_SLIDE_LOSS, WirePairing, WireTrack,
    imu_payload, place_from_wire, place_to_wire, pose_from_wire, pose_to_wire, read_localized,
    write_localized,
};
use nalgebra::UnitQuaternion;

use crate::hypotheses::Hypothesis;
use crate::localize::stamped;
use crate::{Client, ClientError, LocalizeOptions, Localized, TrackedScan};

/// Where a hosted tracker starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HostedStart {
    /// Go on with the session's tracker (a new session's first scan is relocalized).
    Continue,
    /// Start anew, relocalizing the scan (no idea where it is).
    Relocalize,
    /// Start anew at this pose, `T_map_sensor` (a known start).
    At(Pose),
}

impl Client {
    /// Tracks `scan` (sensor frame), taken at `t` seconds on the IMU's clock, with the
    /// session's server-hosted tracker. `options` (pairing distance, iterations, mode)
    /// take effect when the tracker starts (`start` other than `Continue`, or a
    /// session's first scan); the server runs the checks and retry ladder itself.
    pub fn track_hosted(
        &mut self,
        scan: &ScanPayload,
        t: f64,
        start: HostedStart,
        options: &LocalizeOptions,
    ) -> Result<TrackedScan, ClientError> {
        if !t.is_finite() {
            return Err(ClientError::Invalid(format!(
                "the scan time {t} is not finite"
            )));
        }
        let (flags, pose) = match start {
            HostedStart::Continue => (0, Pose::identity()),
            HostedStart::Relocalize => (FLAG_TRACK_RESET, Pose::identity()),
            HostedStart::At(pose) => (FLAG_TRACK_RESET | FLAG_TRACK_FROM_POSE, pose),
        };
        let header = RequestHeader {
            kind: RequestKind::Track as u32,
            pose: pose_to_wire(&pose),
            flags,
            max_iterations: options.max_iterations,
            max_pair_dist: options.max_pair_dist,
            mode: options.mode as u32,
            ..Default::default()
        };
        let r = self
            .connection()
            .call_scan(stamped(header, Some(t)), scan)?;
        tracked_from_wire(&r.header, &r.pairings)
            .map_err(|what| ClientError::Invalid(format!("the server sent {what}")))
    }

    /// Gives the session's hosted tracker IMU samples (on the scans' clock, after the
    /// last ones sent; an IMU mounted at `lidar_from_imu`, `R_lidar_imu`): its gyro
    /// predicts rotation between scans and its accelerometer levels relocalizations.
    /// Returns how many samples the tracker refused (not after the last, not finite).
    pub fn push_hosted_imu(
        &mut self,
        samples: &[ImuSample],
        lidar_from_imu: &UnitQuaternion<f64>,
    ) -> Result<u32, ClientError> {
        let t0 = samples.first().map_or(0.0, |s| s.t);
        let payload = imu_payload(samples, t0);
        let header = RequestHeader {
            kind: RequestKind::TrackImu as u32,
            pose: pose_to_wire(&Pose::from_parts(Default::default(), *lidar_from_imu)),
            imu_t0: t0,
            point_count: samples.len() as u32,
            ..Default::default()
        };
        let r = self.connection().call(header, payload.len(), |_, out| {
            out.copy_from_slice(&payload)
        })?;
        Ok(r.header.track.imu_refused)
    }
}

/// Writes a tracked scan into a `Track` answer: the localization fields and
/// `track`; the places in doubt are returned as the answer's pairings.
pub fn tracked_to_wire(tracked: &TrackedScan, h: &mut ResponseHeader) -> Vec<WirePairing> {
    write_localized(h, &tracked.localized.pose, &tracked.localized.health);
    let mut known = 0;
    let mut figure = |value: Option<f64>, bit: u32| {
        value.map_or(0.0, |v| {
            known |= bit;
            v
        })
    };
    h.track = WireTrack {
        predicted: pose_to_wire(&tracked.predicted),
        t: tracked.t,
        explained: figure(tracked.explained, TRACK_EXPLAINED),
        slide_loss: figure(tracked.slide_loss, TRACK_SLIDE_LOSS),
        max_correction: figure(tracked.max_correction, TRACK_MAX_CORRECTION),
        hypotheses: tracked.hypotheses.len() as u32,
        known,
        ..WireTrack::default()
    };
    tracked
        .hypotheses
        .iter()
        .enumerate()
        .map(|(rank, h)| {
            let mut place = place_to_wire(&h.pose, h.mean_explained(), rank);
            // The rank's slot says how many scans the place was compared on.
            place.rank = h.explained.len() as u64;
            place.to_slot()
        })
        .collect()
}

/// The tracked scan of a `Track` answer. A hypothesis comes back with its mean
/// explained share repeated over the scans it was compared on (its history, misses
/// and incumbency stay with the server's tracker).
pub fn tracked_from_wire(
    h: &ResponseHeader,
    pairings: &[WirePairing],
) -> Result<TrackedScan, String> {
    let (pose, health) = read_localized(h)?;
    let track = &h.track;
    let predicted = pose_from_wire(&track.predicted).ok_or("an invalid predicted pose")?;
    if pairings.len() != track.hypotheses as usize {
        return Err(format!(
            "{} places for {} hypotheses",
            pairings.len(),
            track.hypotheses
        ));
    }
    let hypotheses = pairings
        .iter()
        .map(|slot| {
            let place = kfmap_protocol::WirePlace::from_slot(*slot);
            let pose = place_from_wire(&place).ok_or("a hypothesis with an invalid pose")?;
            let scans = (place.rank as usize).clamp(1, 10_000);
            // The wire carries each place's mean share and scans, not each scan's
            // pinning: what the client shows, not what it decides on.
            Ok(Hypothesis {
                explained: vec![place.score; scans],
                pinned: vec![false; scans],
                ..Hypothesis::new(pose, Some(place.score), false)
            })
        })
        .collect::<Result<Vec<_>, String>>()?;
    let figure = |value: f64, bit: u32| (track.known & bit != 0).then_some(value);
    Ok(TrackedScan {
        t: track.t,
        predicted,
        max_correction: figure(track.max_correction, TRACK_MAX_CORRECTION),
        localized: Localized { pose, health },
        hypotheses,
        explained: figure(track.explained, TRACK_EXPLAINED),
        slide_loss: figure(track.slide_loss, TRACK_SLIDE_LOSS),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use kfmap_geometry::tracking::{Reasons, ScanHealth, TrackingStatus};
    use nalgebra::{Translation3, Vector3};

    /// A tracked scan written into an answer reads back as it was (f32 place rotations
    /// aside), with unknown figures staying unknown.
    #[test]
    fn a_tracked_scan_travels_through_an_answer_unchanged() {
        let at = |x: f64, yaw: f64| {
            Pose::from_parts(
                Translation3::new(x, -2.0, 0.5),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            )
        };
        let mut health = ScanHealth::no_fit(3, 41);
        health.status = TrackingStatus::Degraded;
        health.reasons = Reasons::AMBIGUOUS;
        health.inlier_ratio = 0.71;
        let mut second = Hypothesis::new(at(22.6, 1.6), Some(0.4), false);
        second.explained.push(0.5);
        let tracked = TrackedScan {
            t: 1.7e9 + 0.25,
            predicted: at(1.0, 0.1),
            max_correction: None,
            localized: Localized {
                pose: at(1.1, 0.12),
                health,
            },
            hypotheses: vec![Hypothesis::new(at(1.1, 0.12), Some(0.8), false), second],
            explained: Some(0.8),
            slide_loss: None,
        };
        let mut header = ResponseHeader::default();
        let places = tracked_to_wire(&tracked, &mut header);
        let back = tracked_from_wire(&header, &places).unwrap();
        assert_eq!(back.t, tracked.t);
        assert_eq!(back.predicted, tracked.predicted);
        assert_eq!(back.localized, tracked.localized);
        assert_eq!((back.explained, back.slide_loss), (Some(0.8), None));
        assert_eq!(back.max_correction, None);
        assert_eq!(back.hypotheses.len(), 2);
        assert_eq!(back.hypotheses[1].explained, vec![0.45, 0.45]);
        let gap = back.hypotheses[1].pose.inverse() * tracked.hypotheses[1].pose;
        assert!(gap.translation.vector.norm() < 1e-9 && gap.rotation.angle() < 1e-6);
        // A count that does not match the places is refused, not misread.
        assert!(tracked_from_wire(&header, &places[..1]).is_err());
    }
}
