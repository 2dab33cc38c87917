//! Client library of kfmap: connect to the server of a map over iceoryx2 shared memory
//! and ask for nearest neighbours, cov2cov pairings, a solved pose or a gravity
//! correction. Every call has a timeout; after a timeout the next call reconnects, so
//! a restarted server is found again.
//!
//! ```no_run
//! use kfmap_client::{Client, ClientOptions};
//! use kfmap_geometry::geometry::Pose;
//!
//! let mut client = Client::connect("site", ClientOptions::default())?;
//! let scan = vec![[1.0f32, 0.0, 0.0]; 1000];
//! let found = client.nearest(&scan, &Pose::identity(), 1)?;
//! println!("{} map points, status {:?}", found.len(), client.status()?.sessions);
//! # Ok::<(), kfmap_client::ClientError>(())
//! ```
//!
//! The `kfmap-remote` crate's `connect` reaches a server on another host through its
//! `kfmap gateway` (Zenoh) with a [`Client`] of the same calls and errors, over a
//! [`RemoteLink`].
#![warn(missing_docs)]

mod connection;
mod error;
pub mod hosted;
pub mod hypotheses;
mod localize;
mod relocalize;
mod tracker;

pub use connection::{ClientOptions, Connection, Dispatch, RemoteLink, Response};
pub use error::{ClientError, RemoteError};
pub use hosted::HostedStart;
pub use hypotheses::HypothesisParams;
pub use localize::{LocalizeOptions, Localized};
pub use relocalize::{RelocalizeOptions, Relocalized, ScoredPlace};
pub use tracker::{TrackedScan, Tracker, TrackerOptions, TrustParams};

use kfmap_geometry::KeyframeId;
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::ImuSample;
use kfmap_protocol::{
    Cov2CovMode, KIND_SLOTS, RequestHeader, RequestKind, ScanPayload, WirePairing,
    WireSessionGravity, imu_payload, pose_from_wire, pose_to_wire,
};

/// Cov2cov pairings and the keyframes they came from.
#[derive(Debug, Clone)]
pub struct Cov2CovAnswer {
    /// One pairing per matched scan point, sorted by query index.
    pub pairings: Vec<WirePairing>,
    /// Active keyframe ids.
    pub active: Vec<KeyframeId>,
}

/// A gravity correction from the session's IMU pool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityAnswer {
    /// Keyframes pooled so far.
    pub members: u32,
    /// Gravity estimate, map frame, m/s^2 (`None` while too few keyframes are pooled).
    pub gravity: Option<[f64; 3]>,
    /// Roll and pitch of the correction, radians.
    pub roll_pitch: [f64; 2],
    /// The correction as a quaternion (qx qy qz qw).
    pub correction: [f64; 4],
    /// Members within the Huber threshold of the estimate.
    pub inliers: u32,
    /// Members whose platform acceleration was removed; the correction is only as good
    /// as raw accelerometer means unless this equals `members`.
    pub compensated: u32,
    /// Windows waiting for a stamped pose after them.
    pub pending: u32,
    /// Stamped windows left out: no stamped poses bracketed them.
    pub skipped: u32,
    /// Weighted RMS angle of the members about the estimate, degrees.
    pub spread_deg: f64,
    /// Accelerometer bias estimated with gravity, body frame, m/s^2.
    pub accel_bias_mps2: [f64; 3],
    /// Its standard deviation per axis, m/s^2 (`None` when unknown).
    pub accel_bias_sigma_mps2: Option<[f64; 3]>,
    /// True when the motion so far determines every axis of the bias.
    pub bias_observable: bool,
}

impl GravityAnswer {
    /// A session's pool as a status report lists it (no sigma: not sent there).
    pub fn from_session(g: &WireSessionGravity) -> Self {
        let [roll, pitch] = g.roll_pitch;
        // The server's correction is Ry(pitch) Rx(roll): nalgebra's roll-pitch-yaw order.
        let q = nalgebra::UnitQuaternion::from_euler_angles(roll, pitch, 0.0);
        Self {
            members: g.members,
            gravity: (g.has_gravity == 1).then_some(g.gravity),
            roll_pitch: g.roll_pitch,
            correction: [q.i, q.j, q.k, q.w],
            inliers: g.inliers,
            compensated: g.compensated,
            pending: g.pending,
            skipped: g.skipped,
            spread_deg: g.spread_deg,
            accel_bias_mps2: g.accel_bias,
            accel_bias_sigma_mps2: None,
            bias_observable: g.bias_observable == 1,
        }
    }

    /// True when every pooled member was motion-compensated (and there are members).
    pub fn compensated(&self) -> bool {
        self.members > 0 && self.compensated == self.members
    }
}

/// The server's counters.
#[derive(Debug, Clone)]
pub struct StatusReport {
    /// Map name.
    pub map_name: String,
    /// Map file.
    pub map_path: String,
    /// Keyframes.
    pub keyframes: u64,
    /// Points.
    pub points: u64,
    /// Seconds since the server started.
    pub uptime_s: f64,
    /// Open client sessions.
    pub sessions: u32,
    /// Requests being answered right now, this status request not counted.
    pub in_flight: u32,
    /// `(kind, answered, p50 us, p99 us)` for every kind with requests.
    pub kinds: Vec<(RequestKind, u64, f32, f32)>,
    /// `T_map_input`: how bake moved the dataset's poses into the map frame; apply it to
    /// poses of the baked dataset (e.g. its ground truth) to get map poses.
    pub map_from_input: Pose,
    /// The gravity pool of each session (at most 16, by client id).
    pub session_gravity: Vec<SessionGravity>,
    /// How the server estimates covariances of scans sent without them (its
    /// `server.toml` `[covariance]`).
    pub scan_covariance: CovOptions,
}

/// One session's gravity pool in a status report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionGravity {
    /// The session's client node id.
    pub client: u128,
    /// The session was answering a request and was not read (`pool` is empty).
    pub busy: bool,
    /// Its pool and correction.
    pub pool: GravityAnswer,
}

/// A client of one map server.
pub struct Client {
    connection: Connection,
}

fn header(kind: RequestKind, pose: &Pose) -> RequestHeader {
    RequestHeader {
        kind: kind as u32,
        pose: pose_to_wire(pose),
        ..Default::default()
    }
}

impl Client {
    /// Connects to the server of `map_name`.
    pub fn connect(map_name: &str, options: ClientOptions) -> Result<Self, ClientError> {
        Ok(Self {
            connection: Connection::connect(map_name, options)?,
        })
    }

    /// A client whose requests `dispatch` answers in this process: what a server
    /// gives the tracker it hosts for a session (`client_node`).
    pub fn in_process(map_name: &str, client_node: [u64; 2], dispatch: Box<dyn Dispatch>) -> Self {
        Self {
            connection: Connection::in_process(map_name, client_node, dispatch),
        }
    }

    /// A client over an open connection (e.g. [`Connection::over_remote`]).
    pub fn over(connection: Connection) -> Self {
        Self { connection }
    }

    /// The raw connection (custom requests, tests).
    pub fn connection(&mut self) -> &mut Connection {
        &mut self.connection
    }

    /// The `k` nearest map points of each scan point (sensor frame, moved by `pose`), in
    /// the active keyframes at `pose`.
    pub fn nearest(
        &mut self,
        points: &[[f32; 3]],
        pose: &Pose,
        k: u32,
    ) -> Result<Vec<WirePairing>, ClientError> {
        self.nearest_around(points, pose, k, 0, None)
    }

    /// As [`Self::nearest`], in the `keyframes` keyframes nearest `pose` by position (1
    /// to 64; 0: the active set): the map around a place whichever way it was seen;
    /// with `max_dist` (metres, up to 20), only the neighbours within it: a point with
    /// none near then costs the server little.
    pub fn nearest_around(
        &mut self,
        points: &[[f32; 3]],
        pose: &Pose,
        k: u32,
        keyframes: u32,
        max_dist: Option<f32>,
    ) -> Result<Vec<WirePairing>, ClientError> {
        let h = RequestHeader {
            k,
            keyframes,
            radius: max_dist.unwrap_or(0.0),
            ..header(RequestKind::Nearest, pose)
        };
        Ok(self.connection.call_scan(h, &plain(points))?.pairings)
    }

    /// Every map point within `radius` metres of each scan point.
    pub fn radius(
        &mut self,
        points: &[[f32; 3]],
        pose: &Pose,
        radius: f32,
    ) -> Result<Vec<WirePairing>, ClientError> {
        let h = RequestHeader {
            radius,
            ..header(RequestKind::Radius, pose)
        };
        Ok(self.connection.call_scan(h, &plain(points))?.pairings)
    }

    /// GICP pairings of `scan` at `pose` within `max_pair_dist` metres.
    pub fn cov2cov(
        &mut self,
        scan: &ScanPayload,
        pose: &Pose,
        max_pair_dist: f32,
        mode: Cov2CovMode,
    ) -> Result<Cov2CovAnswer, ClientError> {
        self.cov2cov_with(scan, pose, max_pair_dist, mode, |active, pairings| {
            Cov2CovAnswer {
                active: active.to_vec(),
                pairings: pairings.to_vec(),
            }
        })
    }

    /// As [`Self::cov2cov`], but `read` gets the active keyframe ids and the pairings
    /// in place in shared memory (zero-copy).
    pub fn cov2cov_with<R>(
        &mut self,
        scan: &ScanPayload,
        pose: &Pose,
        max_pair_dist: f32,
        mode: Cov2CovMode,
        read: impl FnOnce(&[u64], &[WirePairing]) -> R,
    ) -> Result<R, ClientError> {
        let h = RequestHeader {
            max_pair_dist,
            mode: mode as u32,
            ..header(RequestKind::Cov2Cov, pose)
        };
        self.connection.call_scan_with(h, scan, |header, pairings| {
            read(&header.active[..header.active_len as usize], pairings)
        })
    }

    /// Adds the IMU window of keyframe (or scan) `id` to this session's gravity pool and
    /// returns the current correction. The window ends at `pose`, taken at `stamp`
    /// (seconds, the samples' clock) and covers the time since the previous window.
    /// With a stamp the server removes the platform's own acceleration, known from the
    /// stamped poses (these and those of server-side localization): the window is
    /// pooled once a pose after it arrives (`pending` until then). Without one it is
    /// pooled as its raw mean, which is only right for a platform at rest.
    pub fn push_imu_window(
        &mut self,
        id: KeyframeId,
        pose: &Pose,
        stamp: Option<f64>,
        samples: &[ImuSample],
    ) -> Result<GravityAnswer, ClientError> {
        let t0 = samples.first().map_or(0.0, |s| s.t);
        let payload = imu_payload(samples, t0);
        let h = RequestHeader {
            keyframe_or_scan_id: id,
            imu_t0: t0,
            point_count: samples.len() as u32,
            ..header(RequestKind::ImuWindow, pose)
        };
        let h = localize::stamped(h, stamp);
        let r = self
            .connection
            .call(h, payload.len(), |_, out| out.copy_from_slice(&payload))?;
        let h = r.header;
        let has = h.has_gravity == 1;
        Ok(GravityAnswer {
            members: h.gravity_members,
            gravity: has.then_some(h.gravity),
            roll_pitch: h.roll_pitch,
            correction: h.correction,
            inliers: h.gravity_inliers,
            compensated: h.gravity_compensated,
            pending: h.gravity_pending,
            skipped: h.gravity_skipped,
            spread_deg: h.gravity_spread_deg,
            accel_bias_mps2: h.accel_bias,
            accel_bias_sigma_mps2: (has && h.accel_bias_sigma != [0.0; 3])
                .then_some(h.accel_bias_sigma),
            bias_observable: h.bias_observable == 1,
        })
    }

    /// The server's counters.
    pub fn status(&mut self) -> Result<StatusReport, ClientError> {
        let r =
            self.connection
                .call(header(RequestKind::Status, &Pose::identity()), 0, |_, _| {})?;
        let h = r.header;
        let scan_covariance = h.scan_covariance.to_options().ok_or_else(|| {
            ClientError::Invalid(format!(
                "the server sent invalid covariance options {:?}",
                h.scan_covariance
            ))
        })?;
        self.connection.served_covariance = Some(scan_covariance);
        let kinds = RequestKind::ALL
            .into_iter()
            .filter(|k| (*k as usize) < KIND_SLOTS && h.counts[*k as usize] > 0)
            .map(|k| {
                let i = k as usize;
                (k, h.counts[i], h.p50_us[i], h.p99_us[i])
            })
            .collect();
        Ok(StatusReport {
            map_name: h.map_name(),
            map_path: h.message(),
            keyframes: h.map_keyframes,
            points: h.map_points,
            uptime_s: h.uptime_s,
            sessions: h.sessions,
            in_flight: h.in_flight,
            kinds,
            map_from_input: pose_from_wire(&h.pose).unwrap_or_else(Pose::identity),
            session_gravity: h
                .session_gravity
                .iter()
                .take(h.sessions as usize)
                .map(|g| SessionGravity {
                    client: (g.client_node[0] as u128) << 64 | g.client_node[1] as u128,
                    busy: g.busy == 1,
                    pool: GravityAnswer::from_session(g),
                })
                .collect(),
            scan_covariance,
        })
    }

    /// How the server estimates the covariances of scans: its `[covariance]`, from a
    /// status report (asked once per connection). Client-side localization estimates
    /// with these, so it registers the same scan as the server would.
    pub fn served_covariance_options(&mut self) -> Result<CovOptions, ClientError> {
        match self.connection.served_covariance {
            Some(options) => Ok(options),
            None => Ok(self.status()?.scan_covariance),
        }
    }

    /// Asks the server to reopen its map file; returns its message.
    pub fn reload(&mut self) -> Result<String, ClientError> {
        let r =
            self.connection
                .call(header(RequestKind::Reload, &Pose::identity()), 0, |_, _| {})?;
        Ok(r.header.message())
    }

    /// A round trip with no work: the server answers with the number of points it got.
    pub fn echo(&mut self, points: &[[f32; 3]]) -> Result<u64, ClientError> {
        let h = header(RequestKind::Echo, &Pose::identity());
        Ok(self.connection.call_scan(h, &plain(points))?.header.detail)
    }
}

fn plain(points: &[[f32; 3]]) -> ScanPayload<'_> {
    ScanPayload {
        points,
        view_dirs: None,
        covariances: None,
    }
}
