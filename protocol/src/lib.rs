//! The map server's wire protocol over iceoryx2 (docs/DESIGN.md#protocol): service
//! names, request kinds, status codes, the `#[repr(C)]` headers and the payload layout,
//! and the checks a server applies to every request before touching the map.
//!
//! ```
//! use kfmap_protocol::{RequestHeader, RequestKind, ScanPayload, decode_scan};
//!
//! let points = [[1.0f32, 2.0, 3.0], [4.0, 5.0, 6.0]];
//! let scan = ScanPayload { points: &points, view_dirs: None, covariances: None };
//! let mut header = RequestHeader { kind: RequestKind::Nearest as u32, ..Default::default() };
//! let payload = scan.encode(&mut header);
//! let decoded = decode_scan(&header, &payload, 1 << 20).unwrap();
//! assert_eq!(decoded.points, &points);
//! ```

mod decode;
mod localized;
pub mod log_limit;
pub mod remote;
pub mod transport;
mod wire;

pub use decode::{
    DecodedScan, Rejection, ScanPayload, check_version, correspondences_from_pairings,
    correspondences_from_wire, decode_imu, decode_scan, decode_stamp, imu_payload,
};
pub use localized::{read_localized, write_localized};
pub use wire::{
    FLAG_COVARIANCES, FLAG_FINISH_CHOSEN, FLAG_LEVELLED, FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN,
    FLAG_STAMPED, FLAG_TRACK_FROM_POSE, FLAG_TRACK_RESET, FLAG_VIEW_DIRS, KIND_SLOTS, MESSAGE_LEN,
    NAME_LEN, PLACES_FROM_RELIEF, RequestHeader, ResponseHeader, STATUS_SESSIONS, TRACK_EXPLAINED,
    TRACK_MAX_CORRECTION, TRACK_SLIDE_LOSS, WireCovOptions, WirePairing, WirePlace, WireRanking,
    WireSessionGravity, WireTrack, read_text, write_text,
};

use kfmap_geometry::geometry::{Pose, pose_from_xyz_quat, pose_to_xyz_quat};
use kfmap_geometry::tracking::Stage;
pub use kfmap_map::map::Cov2CovMode;

/// Version of this protocol; a peer of another version gets `VersionMismatch`.
pub const PROTOCOL_VERSION: u32 = 12;
/// Default limit on points per request.
pub const DEFAULT_MAX_POINTS: usize = 1 << 20;
/// Floats per IMU sample in an `ImuWindow` payload.
pub const IMU_SAMPLE_FLOATS: usize = 7;

/// The request-response service of a map.
pub fn rpc_service_name(map_name: &str) -> String {
    format!("kfmap/{map_name}/rpc")
}

/// Event service clients signal after sending a request.
pub fn request_event_name(map_name: &str) -> String {
    format!("kfmap/{map_name}/request-ready")
}

/// Event service the server signals after answering.
pub fn response_event_name(map_name: &str) -> String {
    format!("kfmap/{map_name}/response-ready")
}

/// What a request asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum RequestKind {
    /// k nearest map points per scan point.
    Nearest = 1,
    /// Every map point within a radius of each scan point.
    Radius = 2,
    /// GICP correspondences with information matrices.
    Cov2Cov = 3,
    /// Server-side GICP: the solved pose.
    Localize = 4,
    /// An IMU window for the session's gravity pool; answers a correction.
    ImuWindow = 5,
    /// Server counters.
    Status = 6,
    /// Answers at once with no work (round-trip measurements).
    Echo = 7,
    /// Reopens the map file and switches to it; requests in flight finish on the old map.
    Reload = 8,
    /// Where a scan was taken, with no pose guess: global relocalization.
    Relocalize = 9,
    /// One scan of the session's server-hosted tracker (new in protocol 10): the
    /// tracker's pose, health, hypotheses and trust figures
    /// (docs/DESIGN.md#hosted-tracking).
    Track = 10,
    /// IMU samples for the session's hosted tracker's gyro (new in protocol 10).
    TrackImu = 11,
}

impl RequestKind {
    /// Every kind, by code order.
    pub const ALL: [RequestKind; 11] = [
        RequestKind::Nearest,
        RequestKind::Radius,
        RequestKind::Cov2Cov,
        RequestKind::Localize,
        RequestKind::ImuWindow,
        RequestKind::Status,
        RequestKind::Echo,
        RequestKind::Reload,
        RequestKind::Relocalize,
        RequestKind::Track,
        RequestKind::TrackImu,
    ];

    /// The kind of a wire code.
    pub fn from_code(code: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|k| *k as u32 == code)
    }

    /// Lower-case name, for logs and reports.
    pub fn name(self) -> &'static str {
        match self {
            RequestKind::Nearest => "nearest",
            RequestKind::Radius => "radius",
            RequestKind::Cov2Cov => "cov2cov",
            RequestKind::Localize => "localize",
            RequestKind::ImuWindow => "imu-window",
            RequestKind::Status => "status",
            RequestKind::Echo => "echo",
            RequestKind::Reload => "reload",
            RequestKind::Relocalize => "relocalize",
            RequestKind::Track => "track",
            RequestKind::TrackImu => "track-imu",
        }
    }

    /// True when the payload is a scan.
    pub fn carries_scan(self) -> bool {
        matches!(
            self,
            RequestKind::Nearest
                | RequestKind::Radius
                | RequestKind::Cov2Cov
                | RequestKind::Localize
                | RequestKind::Relocalize
                | RequestKind::Track
        )
    }
}

/// How a response ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum StatusCode {
    /// Answered.
    Ok = 0,
    /// The scan has no points.
    EmptyScan = 1,
    /// A point (index in `detail`) is NaN or infinite.
    NonFinitePoint = 2,
    /// More points than the server's limit.
    TooManyPoints = 3,
    /// A kind code this server does not know.
    UnknownKind = 4,
    /// The server has no map loaded.
    MapNotLoaded = 5,
    /// The server failed; the message says how.
    Internal = 6,
    /// Client and server speak different protocol versions.
    VersionMismatch = 7,
    /// A parameter or the payload layout is wrong; the message names it.
    BadRequest = 8,
    /// The server is shutting down and did not start this request.
    ShuttingDown = 9,
    /// The request's worst case exceeds a configured limit (the message names it:
    /// `max-answer-bytes`, `max-radius-points`, `client-memory-budget`); sending it
    /// again will not help (new in protocol 5).
    TooLarge = 10,
    /// The request fits the limits, but the memory or request slots it needs are held
    /// by requests in flight (the message names the budget); retry later (new in
    /// protocol 5).
    Busy = 11,
    /// `client_node` is not the node of the port that sent the request (new in
    /// protocol 5).
    NotYourSession = 12,
}

impl StatusCode {
    /// The status of a wire code (unknown codes read as `Internal`).
    pub fn from_code(code: u32) -> Self {
        use StatusCode::*;
        [
            Ok,
            EmptyScan,
            NonFinitePoint,
            TooManyPoints,
            UnknownKind,
            MapNotLoaded,
            Internal,
            VersionMismatch,
            BadRequest,
            ShuttingDown,
            TooLarge,
            Busy,
            NotYourSession,
        ]
        .into_iter()
        .find(|s| *s as u32 == code)
        .unwrap_or(Internal)
    }
}

/// The fine registration stage of localization against a server, the same for the
/// server-side `Localize` and a client iterating over `Cov2Cov` answers, so both land
/// on the same pose ([`Stage::params`] gives the registration settings).
pub fn localize_stage(max_pair_dist: f32, max_iterations: u32) -> Stage {
    Stage {
        coarse: false,
        max_pair_dist: max_pair_dist as f64,
        max_iterations: max_iterations as usize,
    }
}

/// A pose as it travels: x, y, z, qx, qy, qz, qw.
pub fn pose_to_wire(pose: &Pose) -> [f64; 7] {
    pose_to_xyz_quat(pose)
}

/// The pose of a wire array; `None` when non-finite or the quaternion is not unit
/// length within 1e-3.
pub fn pose_from_wire(values: &[f64; 7]) -> Option<Pose> {
    if values.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let norm = values[3..].iter().map(|v| v * v).sum::<f64>().sqrt();
    if (norm - 1.0).abs() >= 1e-3 {
        return None;
    }
    pose_from_xyz_quat(*values)
}

/// A place of rank `rank` with its score, as a `FLAG_PLACES_ONLY` or
/// `FLAG_SCORE_CHOSEN` answer carries it.
pub fn place_to_wire(pose: &Pose, score: f64, rank: usize) -> WirePlace {
    let [x, y, z, qx, qy, qz, qw] = pose_to_wire(pose);
    WirePlace {
        translation: [x, y, z],
        rotation: [qx as f32, qy as f32, qz as f32, qw as f32],
        score,
        rank: rank as u64,
    }
}

/// The pose of a proposed place (`None` when not finite or not a rotation).
pub fn place_from_wire(place: &WirePlace) -> Option<Pose> {
    let [x, y, z] = place.translation;
    let q = place.rotation.map(f64::from);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    // Unit in f32; renormalized in f64 before the strict check.
    if !norm.is_finite() || (norm - 1.0).abs() >= 1e-3 {
        return None;
    }
    pose_from_wire(&[x, y, z, q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm])
}

#[cfg(test)]
mod tests;
