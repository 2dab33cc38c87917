//! Global relocalization of one scan by the server (`Relocalize`): no pose guess.

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::tracking::covariance_from_wire;
use kfmap_map::place::RelocalizeStatus;
use kfmap_protocol::{
    FLAG_LEVELLED, RequestHeader, RequestKind, ScanPayload, WirePlace, place_from_wire,
    pose_from_wire, pose_to_wire,
};
use nalgebra::{Matrix6, UnitQuaternion};

use crate::{Client, ClientError};

/// Relocalization settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelocalizeOptions {
    /// Largest pairing distance of the verifying registrations, metres.
    pub max_pair_dist: f32,
    /// Iterations of the final registration at most.
    pub max_iterations: u32,
    /// The sensor's tilt (roll and pitch, e.g. from an IMU's gravity) as a rotation
    /// `R_world_sensor` whose yaw is ignored; `None`: the server finds up in the scan.
    pub tilt: Option<UnitQuaternion<f64>>,
}

impl Default for RelocalizeOptions {
    fn default() -> Self {
        Self {
            max_pair_dist: 1.0,
            max_iterations: 30,
            tilt: None,
        }
    }
}

/// A place the server scored for a scan: where the scan settled there, and its score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoredPlace {
    /// `T_map_sensor` where the scan settled (coarse scan, fine pairing distance).
    pub pose: Pose,
    /// Share of the coarse scan paired at the fine distance there.
    pub score: f64,
}

/// Where the server placed a scan.
#[derive(Debug, Clone, PartialEq)]
pub struct Relocalized {
    /// `found`, `ambiguous` or `not-found`.
    pub status: RelocalizeStatus,
    /// `T_map_sensor` of the best place; `None` when `not-found`.
    pub pose: Option<Pose>,
    /// Share of the scan paired at `max_pair_dist` at that pose.
    pub inlier_ratio: f64,
    /// RMS of the paired distances there, metres.
    pub rmse: f64,
    /// Share of the scan paired within 0.3 times `max_pair_dist` there.
    pub tight_inlier_ratio: f64,
    /// The final registration's Hessian is degenerate.
    pub degenerate: bool,
    /// The final registration converged.
    pub converged: bool,
    /// The best place's verification score and the best other place's (0: none).
    pub score: f64,
    /// See `score`.
    pub runner_up: f64,
    /// Places the server's search proposed.
    pub candidates: u32,
    /// Every place the server scored, best score first (over a tile set, every tile's;
    /// empty from a server too old to send them): a tracker keeps those near the best
    /// as hypotheses.
    pub places: Vec<ScoredPlace>,
    /// 6x6 pose covariance (rotation first), when known.
    pub covariance: Option<Matrix6<f64>>,
    /// Server compute time, microseconds.
    pub server_us: f64,
}

impl Client {
    /// Asks the server where `scan` (sensor frame) was taken in its map.
    pub fn relocalize(
        &mut self,
        scan: &ScanPayload,
        options: &RelocalizeOptions,
    ) -> Result<Relocalized, ClientError> {
        let tilt = options.tilt.unwrap_or_else(UnitQuaternion::identity);
        let header = RequestHeader {
            kind: RequestKind::Relocalize as u32,
            pose: pose_to_wire(&Pose::from_parts(Default::default(), tilt)),
            max_iterations: options.max_iterations,
            max_pair_dist: options.max_pair_dist,
            flags: if options.tilt.is_some() {
                FLAG_LEVELLED
            } else {
                0
            },
            ..Default::default()
        };
        let r = self.connection().call_scan(header, scan)?;
        let h = r.header;
        let invalid = |what: String| ClientError::Invalid(format!("the server sent {what}"));
        let status = RelocalizeStatus::from_code(h.relocalization).ok_or_else(|| {
            invalid(format!(
                "an unknown relocalization status {}",
                h.relocalization
            ))
        })?;
        let pose = match status {
            RelocalizeStatus::NotFound => None,
            _ => Some(pose_from_wire(&h.pose).ok_or_else(|| invalid("an invalid pose".into()))?),
        };
        let mut places: Vec<ScoredPlace> = r
            .pairings
            .iter()
            .map(|slot| {
                let place = WirePlace::from_slot(*slot);
                let pose = place_from_wire(&place)
                    .ok_or_else(|| invalid("a scored place with an invalid pose".into()))?;
                Ok(ScoredPlace {
                    pose,
                    score: place.score,
                })
            })
            .collect::<Result<_, ClientError>>()?;
        places.sort_by(|a, b| b.score.total_cmp(&a.score));
        Ok(Relocalized {
            places,
            status,
            pose,
            inlier_ratio: h.fitness[0],
            rmse: h.fitness[1],
            tight_inlier_ratio: h.tight_fitness,
            degenerate: h.degenerate == 1,
            converged: h.converged == 1,
            score: h.place_scores[0],
            runner_up: h.place_scores[1],
            candidates: h.candidates,
            covariance: covariance_from_wire(&h.covariance),
            server_us: h.server_us,
        })
    }
}
