//! The `#[repr(C)]` types on the wire. Layouts and type names are stable within a
//! protocol version, so clients built on iceoryx2's C, C++ or Python bindings can speak
//! the protocol (docs/DESIGN.md#protocol).

// `Pod` fails to compile on any padding: the byte frames of remote requests
// (crate::remote) rely on it.
use bytemuck::{Pod, Zeroable};
use iceoryx2::prelude::ZeroCopySend;
use kfmap_geometry::cov::{CovCenter, CovOptions};
use kfmap_map::tiles::PlaceRanking;

/// Bytes of a response's status message (UTF-8, zero padded).
pub const MESSAGE_LEN: usize = 240;
/// Request kinds counted in a status report (index = kind code).
pub const KIND_SLOTS: usize = 12;
/// Bytes of the map name in a status report.
pub const NAME_LEN: usize = 64;
/// Sessions whose gravity pool a status report lists, at most.
pub const STATUS_SESSIONS: usize = 16;

/// Header of every request. The payload is `[f32]`: for scan requests `3 n` point
/// coordinates (sensor frame, metres), then `3 n` view directions when
/// `flags & FLAG_VIEW_DIRS`, then `6 n` packed covariances (xx xy xz yy yz zz, m^2) when
/// `flags & FLAG_COVARIANCES`; for IMU windows `7 n` values per sample (seconds after
/// `imu_t0`, specific force xyz m/s^2, angular rate xyz rad/s).
///
/// Layout (protocol 4, 152 bytes, byte offsets): version 0, kind 4, request_id 8,
/// client_node 16, pose 32, point_count 88, flags 92, k 96, mode 100, radius 104,
/// max_pair_dist 108, max_iterations 112, max_correction 116 (was `reserved` in
/// protocol 2), keyframe_or_scan_id 120, imu_t0 128, expected_inlier_ratio 136 (new
/// in protocol 3), keyframes 140 (was `reserved` before protocol 11), stamp 144 (new in
/// protocol 4).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::RequestHeader")]
pub struct RequestHeader {
    /// [`super::PROTOCOL_VERSION`] of the sender.
    pub version: u32,
    /// [`super::RequestKind`] code.
    pub kind: u32,
    /// Chosen by the client, echoed in the response.
    pub request_id: u64,
    /// The client's iceoryx2 node id (high word first): its session (active set, gravity
    /// pool) lives until that node is gone.
    pub client_node: [u64; 2],
    /// Pose guess `T_map_sensor`: x, y, z (metres), qx, qy, qz, qw.
    pub pose: [f64; 7],
    /// Points (or IMU samples) in the payload.
    pub point_count: u32,
    /// `FLAG_*` bits: which optional arrays follow the points.
    pub flags: u32,
    /// Neighbours per point (`Nearest`).
    pub k: u32,
    /// [`super::Cov2CovMode`] code (`Cov2Cov`, `Localize`).
    pub mode: u32,
    /// Search radius, metres (`Radius`); `Nearest`: when above 0, only the neighbours
    /// within it (inclusive), 0 = at any distance (new in protocol 12).
    pub radius: f32,
    /// Largest pairing distance, metres (`Cov2Cov`, `Localize`).
    pub max_pair_dist: f32,
    /// Iterations at most (`Localize`).
    pub max_iterations: u32,
    /// `Localize`: the largest correction from the pose guess (the client's prediction)
    /// its motion model allows, metres of translation plus the chord a point at
    /// [`kfmap_geometry::tracking::CORRECTION_RANGE_M`] sweeps; 0 = no motion model (no bound).
    pub max_correction: f32,
    /// Keyframe or scan the IMU window belongs to (`ImuWindow`); `Relocalize` with
    /// `FLAG_SCORE_CHOSEN` or `FLAG_FINISH_CHOSEN`: the ranks chosen, bit r for rank r.
    pub keyframe_or_scan_id: u64,
    /// Time origin of the IMU samples, seconds (`ImuWindow`).
    pub imu_t0: f64,
    /// `Localize`: the inlier ratio the client's tracker expects (that of its scans
    /// before); a first registration well below it is retried. 0 = unknown.
    pub expected_inlier_ratio: f32,
    /// `Nearest`: search this many keyframes, those nearest the pose by position (1 to 64)
    /// instead of the active set; 0 = the active set.
    pub keyframes: u32,
    /// With `FLAG_STAMPED`: the time `pose` was taken at, seconds on the IMU's clock
    /// (`Localize`: the scan's; `ImuWindow`: the window's end, its keyframe's). The
    /// session keeps these stamped poses to remove the platform's own acceleration
    /// from its IMU windows.
    pub stamp: f64,
}

/// View directions follow the points.
pub const FLAG_VIEW_DIRS: u32 = 1;
/// Packed covariances follow the points (and view directions).
pub const FLAG_COVARIANCES: u32 = 2;
/// `stamp` holds the pose's time.
pub const FLAG_STAMPED: u32 = 4;
/// `Relocalize`: the pose guess's rotation gives the sensor's tilt (roll and pitch from
/// an IMU), its yaw and position are ignored; without it, up is found from the scan.
pub const FLAG_LEVELLED: u32 = 8;
/// `Relocalize`: answer the search's proposed places ([`WirePlace`]s in the pairings'
/// slots, best first) without verifying any: the first phase of a relocalization over
/// a tile set, whose client ranks every tile's places as one search would.
pub const FLAG_PLACES_ONLY: u32 = 16;
/// `Relocalize`: settle and score only the proposed places whose ranks are set in
/// `keyframe_or_scan_id` (bit r: the r-th best place of this scan's search) and answer
/// them ([`WirePlace`]s: settled pose, score, rank), deciding nothing: the second phase
/// over a tile set. The session keeps the search's places and these scores, so nothing
/// runs twice for the same scan.
pub const FLAG_SCORE_CHOSEN: u32 = 32;
/// `Relocalize`: the final registration of the scored place whose rank is the one bit
/// set in `keyframe_or_scan_id`, answered as a relocalization of that place alone
/// (found when it fits, no runner-up): the third phase over a tile set, on the tile of
/// the best score of them all.
pub const FLAG_FINISH_CHOSEN: u32 = 64;
/// `Track`: start the session's tracker anew with this scan, from `pose` when
/// `FLAG_TRACK_FROM_POSE` is set, else relocalizing (the gyro's log is kept). The
/// first `Track` of a session starts one either way; its `max_pair_dist`,
/// `max_iterations` and `mode` hold until the next start.
pub const FLAG_TRACK_RESET: u32 = 128;
/// `Track` with `FLAG_TRACK_RESET`: the tracker starts at `pose` (a known start).
pub const FLAG_TRACK_FROM_POSE: u32 = 256;
/// `ResponseHeader::reasons` of a `FLAG_PLACES_ONLY` answer: the places come from the
/// relief search (uphill ground kept), which a server runs when its structure search
/// proposes nothing. Over a tile set they stand only when no tile proposed from
/// structure, as one search of the whole map decides.
pub const PLACES_FROM_RELIEF: u32 = 1;

impl Default for RequestHeader {
    fn default() -> Self {
        Self {
            version: super::PROTOCOL_VERSION,
            kind: 0,
            request_id: 0,
            client_node: [0; 2],
            pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            point_count: 0,
            flags: 0,
            k: 1,
            mode: 0,
            radius: 0.0,
            max_pair_dist: 0.0,
            max_iterations: 0,
            max_correction: 0.0,
            keyframe_or_scan_id: 0,
            imu_t0: 0.0,
            expected_inlier_ratio: 0.0,
            keyframes: 0,
            stamp: 0.0,
        }
    }
}

/// One answer element: a map point found for query point `query`. Nearest and radius
/// answers leave `information` zero; cov2cov answers carry `(C_map + R C_q R^T)^-1`.
///
/// Layout (56 bytes): query 0, local_index 4, keyframe 8, point 16, dist_sq 28,
/// information 32.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::WirePairing")]
pub struct WirePairing {
    /// Index of the query point in the request.
    pub query: u32,
    /// Local index of the map point in its keyframe.
    pub local_index: u32,
    /// Keyframe holding the map point.
    pub keyframe: u64,
    /// The map point, map frame, metres.
    pub point: [f32; 3],
    /// Squared distance to the (moved) query point, m^2.
    pub dist_sq: f32,
    /// Packed information matrix (xx xy xz yy yz zz), 1/m^2, map frame.
    pub information: [f32; 6],
}

/// One place of a relocalization over a tile set (`FLAG_PLACES_ONLY`: as proposed;
/// `FLAG_SCORE_CHOSEN`: as settled and scored), written in the slot of a
/// [`WirePairing`] (same size and alignment; [`WirePlace::from_slot`] and
/// [`WirePlace::to_slot`] convert).
///
/// Layout (56 bytes): translation 0 (f64 x y z, metres, map frame), rotation 24 (f32
/// qx qy qz qw of `R_map_sensor`), score 40 (f64), rank 48 (u64).
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct WirePlace {
    /// Position of the sensor, map frame, metres.
    pub translation: [f64; 3],
    /// Orientation (x y z w); f32 is ample to tell places apart (the server keeps its own
    /// places in f64 for the phases after).
    pub rotation: [f32; 4],
    /// Proposed: the search's hit ratio (share of its points that hit the map). Scored:
    /// the share of the coarse scan paired at the fine distance.
    pub score: f64,
    /// The place's rank in its server's search (0: the best hit ratio there).
    pub rank: u64,
}

impl WirePlace {
    /// The place written in a pairing's slot.
    pub fn to_slot(self) -> WirePairing {
        bytemuck::cast(self)
    }

    /// The place a pairing's slot holds.
    pub fn from_slot(slot: WirePairing) -> Self {
        bytemuck::cast(slot)
    }
}

/// Header of every response; the payload is `[WirePairing]`.
///
/// Layout (protocol 10, 3416 bytes, byte offsets): version 0, status 4, request_id 8,
/// detail 16, message_len 24, active_len 28, active 32, server_us 160, pose 168,
/// covariance 224, fitness 512, iterations 528, converged 532, tracking 536 (new in
/// protocol 3, as the next five), reasons 540, registrations 544, degenerate 548,
/// constraint 552, pose_correction 568, relocalization 576 (new in protocol 6, as the
/// next three), candidates 580, place_scores 584, tight_fitness 600, has_gravity 608,
/// gravity_members 612, gravity 616, roll_pitch 640, correction 656, gravity_inliers
/// 688 (new in protocol 4, as the next eight), gravity_compensated 692,
/// gravity_pending 696, gravity_skipped 700, bias_observable 704, gravity_reserved
/// 708, gravity_spread_deg 712, accel_bias 720, accel_bias_sigma 744, map_keyframes
/// 768, map_points 776, uptime_s 784, counts 792, p50_us 888, p99_us 936, sessions
/// 984, in_flight 988, map_name_len 992, map_name 996, message 1060, message_reserved 1300, session_gravity
/// 1304 (new in protocol 4), scan_covariance 3224 (new in protocol 7),
/// relocalize_ranking 3264 (new in protocol 9), track 3312 (new in protocol 10; from
/// protocol 10 `counts`, `p50_us` and `p99_us` hold 12 kinds, so everything after
/// `counts` moved by 32 bytes).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::ResponseHeader")]
pub struct ResponseHeader {
    /// [`super::PROTOCOL_VERSION`] of the server.
    pub version: u32,
    /// [`super::StatusCode`] code.
    pub status: u32,
    /// The request's id.
    pub request_id: u64,
    /// Error detail, e.g. the index of the first non-finite point.
    pub detail: u64,
    /// Bytes used in `message`.
    pub message_len: u32,
    /// Active keyframes used (first `active_len` of `active`).
    pub active_len: u32,
    /// Active keyframe ids.
    pub active: [u64; 16],
    /// Server compute time, microseconds.
    pub server_us: f64,
    /// `Localize`: solved `T_map_sensor` (x y z qx qy qz qw). `Status`: `T_map_input`,
    /// how bake moved the input poses into the map frame (gravity levelling).
    pub pose: [f64; 7],
    /// `Localize`: 6x6 pose covariance, row-major, all zero when unknown: calibrated
    /// (the residual-scaled inverse Hessian plus the cluster-robust sandwich, inflated,
    /// with a rotation floor), of the perturbation `T exp(d)` with `d` = (rotation
    /// rad, translation m) in the sensor frame, rotation first
    /// ([`kfmap_geometry::tracking::pose_covariance`]; `Track` adds the slide's
    /// widening).
    pub covariance: [f64; 36],
    /// `Localize`: inlier ratio and RMSE (metres).
    pub fitness: [f64; 2],
    /// `Localize`: solver iterations over every registration run; 1 in `converged`
    /// when the registration the pose came from converged.
    pub iterations: u32,
    /// See `iterations`.
    pub converged: u32,
    /// `Localize`: [`kfmap_geometry::tracking::TrackingStatus`] code (0 ok, 1 degraded, 2 lost;
    /// lost answers carry the pose guess).
    pub tracking: u32,
    /// `Localize`: [`kfmap_geometry::tracking::Reasons`] bits.
    pub reasons: u32,
    /// `Localize`: registrations run (1 when the first passed every check).
    pub registrations: u32,
    /// `Localize`: 1 when the Hessian is degenerate.
    pub degenerate: u32,
    /// `Localize`: min/max eigenvalue ratios of the Hessian's rotation and translation
    /// blocks.
    pub constraint: [f64; 2],
    /// `Localize`: correction from the pose guess, metres (as `max_correction`).
    pub pose_correction: f64,
    /// `Relocalize`: [`kfmap_map::place::RelocalizeStatus`] code (0 found, 1 ambiguous,
    /// 2 not-found). `pose`, `covariance`, `fitness` are the best place's.
    pub relocalization: u32,
    /// `Relocalize`: places the search proposed (each verified by registration).
    pub candidates: u32,
    /// `Relocalize`: the best place's verification score and the best other place's
    /// (share of the coarse scan paired at the request's distance; 0: none).
    pub place_scores: [f64; 2],
    /// `Relocalize`: share of the scan paired within 0.3 times the request's distance
    /// at the answered pose (`found` needs 0.4).
    pub tight_fitness: f64,
    /// `ImuWindow`: 1 when a correction is available.
    pub has_gravity: u32,
    /// `ImuWindow`: keyframes pooled in this session.
    pub gravity_members: u32,
    /// `ImuWindow`: gravity estimate in the map frame, m/s^2.
    pub gravity: [f64; 3],
    /// `ImuWindow`: roll and pitch of the correction, radians.
    pub roll_pitch: [f64; 2],
    /// `ImuWindow`: correction rotation (qx qy qz qw).
    pub correction: [f64; 4],
    /// `ImuWindow`: pool members within the Huber threshold of the estimate.
    pub gravity_inliers: u32,
    /// `ImuWindow`: pool members whose platform acceleration was removed (the rest
    /// are raw means: the session's stamped poses did not cover them closely enough).
    /// The correction is only as good as a raw mean unless this equals
    /// `gravity_members`.
    pub gravity_compensated: u32,
    /// `ImuWindow`: windows held until a stamped pose after them arrives (their
    /// platform acceleration needs the motion on both sides); pooled then.
    pub gravity_pending: u32,
    /// `ImuWindow`: stamped windows left out because the session's stamped poses did
    /// not bracket them (two on each side, at most 1 s apart).
    pub gravity_skipped: u32,
    /// `ImuWindow`: 1 when the motion so far determines every axis of the bias.
    pub bias_observable: u32,
    /// Reserved, zero.
    pub gravity_reserved: u32,
    /// `ImuWindow`: weighted RMS angle of the members about the estimate, degrees.
    pub gravity_spread_deg: f64,
    /// `ImuWindow`: accelerometer bias estimated with gravity, body frame, m/s^2.
    pub accel_bias: [f64; 3],
    /// `ImuWindow`: its standard deviation per axis, m/s^2 (zero when unknown).
    pub accel_bias_sigma: [f64; 3],
    /// `Status`: keyframes and points of the map.
    pub map_keyframes: u64,
    /// See `map_keyframes`.
    pub map_points: u64,
    /// `Status`: seconds since the server started.
    pub uptime_s: f64,
    /// `Status`: requests answered per kind code.
    pub counts: [u64; KIND_SLOTS],
    /// `Status`: median latency per kind, microseconds.
    pub p50_us: [f32; KIND_SLOTS],
    /// `Status`: 99th percentile latency per kind, microseconds.
    pub p99_us: [f32; KIND_SLOTS],
    /// `Status`: open sessions.
    pub sessions: u32,
    /// `Status`: requests being answered right now (taken by a worker, not yet sent).
    pub in_flight: u32,
    /// `Status`: bytes used in `map_name`.
    pub map_name_len: u32,
    /// `Status`: the served map's name.
    pub map_name: [u8; NAME_LEN],
    /// Status message (UTF-8).
    pub message: [u8; MESSAGE_LEN],
    /// Reserved, zero: the four bytes before `session_gravity` that `#[repr(C)]` would
    /// pad anyway, named so every byte of the header is defined.
    pub message_reserved: u32,
    /// `Status`: the gravity pool of each session (the first `min(sessions, 16)`, by
    /// client id); unused slots are zero.
    pub session_gravity: [WireSessionGravity; STATUS_SESSIONS],
    /// `Status`: how the server estimates the covariances of scans sent without them
    /// (`server.toml` `[covariance]`). A client that estimates its own (client-side
    /// localization) uses these, so both sides register the same scan alike.
    pub scan_covariance: WireCovOptions,
    /// `Status`: how the server ranks relocalization places (`server.toml`
    /// `[relocalize]`); a gateway publishes them with a tile set's index, so clients
    /// merging tiles rank as the servers do.
    pub relocalize_ranking: WireRanking,
    /// `Track` and `TrackImu`: what the session's hosted tracker adds to a
    /// localization.
    pub track: WireTrack,
}

/// What a hosted tracker says of one scan beside the localization fields of the
/// header (`Track`); the places still in doubt follow as [`WirePlace`]s in the
/// pairings' slots (score: the mean share of the scans' structure explained there,
/// rank: scans compared), best first.
///
/// Layout (104 bytes): predicted 0, t 56, explained 64, slide_loss 72,
/// max_correction 80, hypotheses 88, known 92, imu_refused 96, reserved 100.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::WireTrack")]
pub struct WireTrack {
    /// The motion model's prediction the scan was localized from, `T_map_sensor`
    /// (x y z qx qy qz qw).
    pub predicted: [f64; 7],
    /// The scan's time, seconds (the request's stamp).
    pub t: f64,
    /// Share of the scan's structure the map explains at the pose (`TRACK_EXPLAINED`).
    pub explained: f64,
    /// What a 0.5 m slide along the least constrained direction loses of it
    /// (`TRACK_SLIDE_LOSS`).
    pub slide_loss: f64,
    /// The correction bound used, metres (`TRACK_MAX_CORRECTION`).
    pub max_correction: f64,
    /// Places in doubt (as many [`WirePlace`]s follow); 0 while one place is tracked.
    pub hypotheses: u32,
    /// `TRACK_*` bits: which of the optional figures above are known.
    pub known: u32,
    /// `TrackImu`: samples refused (not after the last, or not finite).
    pub imu_refused: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// [`WireTrack::explained`] holds a figure.
pub const TRACK_EXPLAINED: u32 = 1;
/// [`WireTrack::slide_loss`] holds a figure.
pub const TRACK_SLIDE_LOSS: u32 = 2;
/// [`WireTrack::max_correction`] holds a figure.
pub const TRACK_MAX_CORRECTION: u32 = 4;

/// A server's place-ranking settings as a status report carries them
/// ([`kfmap_map::tiles::PlaceRanking`]).
///
/// Layout (48 bytes): keep_ratio 0, separation_m 8, separation_deg 16,
/// ambiguity_margin 24, distinct_m 32, distinct_deg 40.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::WireRanking")]
pub struct WireRanking {
    /// `[relocalize.search] keep-ratio`.
    pub keep_ratio: f64,
    /// `[relocalize.search] separation-m`.
    pub separation_m: f64,
    /// `[relocalize.search] separation-deg`.
    pub separation_deg: f64,
    /// `[relocalize] ambiguity-margin`.
    pub ambiguity_margin: f64,
    /// `[relocalize] distinct-m`.
    pub distinct_m: f64,
    /// `[relocalize] distinct-deg`.
    pub distinct_deg: f64,
}

impl From<&PlaceRanking> for WireRanking {
    fn from(r: &PlaceRanking) -> Self {
        Self {
            keep_ratio: r.keep_ratio,
            separation_m: r.separation_m,
            separation_deg: r.separation_deg,
            ambiguity_margin: r.ambiguity_margin,
            distinct_m: r.distinct_m,
            distinct_deg: r.distinct_deg,
        }
    }
}

impl WireRanking {
    /// The settings, when valid ([`PlaceRanking::validate`]).
    pub fn to_ranking(&self) -> Option<PlaceRanking> {
        let ranking = PlaceRanking {
            keep_ratio: self.keep_ratio,
            separation_m: self.separation_m,
            separation_deg: self.separation_deg,
            ambiguity_margin: self.ambiguity_margin,
            distinct_m: self.distinct_m,
            distinct_deg: self.distinct_deg,
        };
        ranking.validate().ok().map(|()| ranking)
    }
}

/// Covariance-estimation options as a status report carries them
/// ([`kfmap_geometry::cov::CovOptions`]).
///
/// Layout (40 bytes): k_correspondences 0, min_correspondences 4, center 8, reserved
/// 12, max_distance 16, lambda 24, max_plane_deviation 32.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::WireCovOptions")]
pub struct WireCovOptions {
    /// Neighbours searched per point (k).
    pub k_correspondences: u32,
    /// Fewer neighbours than this give the isotropic fallback.
    pub min_correspondences: u32,
    /// Centre of the scatter: 0 the neighbourhood mean, 1 the query point.
    pub center: u32,
    /// Reserved, zero.
    pub reserved: u32,
    /// Neighbours lie strictly closer than this, metres.
    pub max_distance: f64,
    /// Regularization (see `CovOptions::lambda`).
    pub lambda: f64,
    /// Plane-deviation gate, metres (0: off).
    pub max_plane_deviation: f64,
}

impl From<&CovOptions> for WireCovOptions {
    fn from(o: &CovOptions) -> Self {
        Self {
            k_correspondences: o.k_correspondences_for_cov as u32,
            min_correspondences: o.min_correspondences_for_cov as u32,
            center: match o.cov_center {
                CovCenter::Mean => 0,
                CovCenter::Query => 1,
            },
            reserved: 0,
            max_distance: o.max_distance_for_cov,
            lambda: o.lambda,
            max_plane_deviation: o.max_plane_deviation_for_cov,
        }
    }
}

impl WireCovOptions {
    /// The options, when they are valid ones (`None` for an unknown centre code or a
    /// value `CovOptions::validate` refuses).
    pub fn to_options(&self) -> Option<CovOptions> {
        let options = CovOptions {
            k_correspondences_for_cov: self.k_correspondences as usize,
            min_correspondences_for_cov: self.min_correspondences as usize,
            max_distance_for_cov: self.max_distance,
            lambda: self.lambda,
            cov_center: match self.center {
                0 => CovCenter::Mean,
                1 => CovCenter::Query,
                _ => return None,
            },
            max_plane_deviation_for_cov: self.max_plane_deviation,
        };
        options.validate().ok().map(|()| options)
    }
}

/// One session's gravity pool in a status report.
///
/// Layout (120 bytes): client_node 0, members 16, compensated 20, pending 24, skipped
/// 28, inliers 32, has_gravity 36, bias_observable 40, busy 44, roll_pitch 48,
/// spread_deg 64, accel_bias 72, gravity 96.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("kfmap::WireSessionGravity")]
pub struct WireSessionGravity {
    /// The client's node id (as in requests); zero for an unused slot.
    pub client_node: [u64; 2],
    /// Pool members, and those motion-compensated.
    pub members: u32,
    /// See `members`.
    pub compensated: u32,
    /// Windows waiting for a later pose, and stamped windows left out.
    pub pending: u32,
    /// See `pending`.
    pub skipped: u32,
    /// Members within the Huber threshold.
    pub inliers: u32,
    /// 1 when the pool gives a correction.
    pub has_gravity: u32,
    /// 1 when the motion so far determines the accelerometer bias.
    pub bias_observable: u32,
    /// 1 when the session was answering a request and was not read.
    pub busy: u32,
    /// Roll and pitch of the correction, radians.
    pub roll_pitch: [f64; 2],
    /// Weighted RMS angle of the members about the estimate, degrees.
    pub spread_deg: f64,
    /// Accelerometer bias, body frame, m/s^2.
    pub accel_bias: [f64; 3],
    /// Gravity estimate in the map frame, m/s^2.
    pub gravity: [f64; 3],
}

impl Default for ResponseHeader {
    fn default() -> Self {
        Self {
            version: super::PROTOCOL_VERSION,
            status: 0,
            request_id: 0,
            detail: 0,
            message_len: 0,
            active_len: 0,
            active: [0; 16],
            server_us: 0.0,
            pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            covariance: [0.0; 36],
            fitness: [0.0; 2],
            iterations: 0,
            converged: 0,
            tracking: 0,
            reasons: 0,
            registrations: 0,
            degenerate: 0,
            constraint: [0.0; 2],
            pose_correction: 0.0,
            relocalization: 0,
            candidates: 0,
            place_scores: [0.0; 2],
            tight_fitness: 0.0,
            has_gravity: 0,
            gravity_members: 0,
            gravity: [0.0; 3],
            roll_pitch: [0.0; 2],
            correction: [0.0, 0.0, 0.0, 1.0],
            gravity_inliers: 0,
            gravity_compensated: 0,
            gravity_pending: 0,
            gravity_skipped: 0,
            bias_observable: 0,
            gravity_reserved: 0,
            gravity_spread_deg: 0.0,
            accel_bias: [0.0; 3],
            accel_bias_sigma: [0.0; 3],
            map_keyframes: 0,
            map_points: 0,
            uptime_s: 0.0,
            counts: [0; KIND_SLOTS],
            p50_us: [0.0; KIND_SLOTS],
            p99_us: [0.0; KIND_SLOTS],
            sessions: 0,
            in_flight: 0,
            map_name_len: 0,
            map_name: [0; NAME_LEN],
            message: [0; MESSAGE_LEN],
            message_reserved: 0,
            session_gravity: [WireSessionGravity::default(); STATUS_SESSIONS],
            scan_covariance: WireCovOptions::default(),
            relocalize_ranking: WireRanking::default(),
            track: WireTrack::default(),
        }
    }
}

/// Copies `text` into a fixed buffer, cut at a character boundary; returns bytes used.
pub fn write_text<const N: usize>(buffer: &mut [u8; N], text: &str) -> u32 {
    let mut end = text.len().min(N);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    buffer[..end].copy_from_slice(&text.as_bytes()[..end]);
    buffer[end..].fill(0);
    end as u32
}

/// The text in a fixed buffer (lossy on invalid UTF-8 from a foreign client).
pub fn read_text(buffer: &[u8], len: u32) -> String {
    let len = (len as usize).min(buffer.len());
    String::from_utf8_lossy(&buffer[..len]).into_owned()
}

impl ResponseHeader {
    /// The status message.
    pub fn message(&self) -> String {
        read_text(&self.message, self.message_len)
    }

    /// The map name of a status report.
    pub fn map_name(&self) -> String {
        read_text(&self.map_name, self.map_name_len)
    }

    /// Sets the status message.
    pub fn set_message(&mut self, text: &str) {
        self.message_len = write_text(&mut self.message, text);
    }

    /// An answer refusing request `request_id` with `status` and `message`.
    pub fn refusal(request_id: u64, status: super::StatusCode, message: &str) -> Self {
        let mut header = Self {
            status: status as u32,
            request_id,
            ..Default::default()
        };
        header.set_message(message);
        header
    }
}
