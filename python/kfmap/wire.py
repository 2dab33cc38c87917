"""The kfmap wire protocol (protocol 12): the ``#[repr(C)]`` headers as ctypes
structures, request kinds, flags and status codes.

Mirrors ``protocol/src/wire.rs`` and ``lib.rs``. iceoryx2 refuses to open a
service whose payload or header types differ from the server's in name, size or
alignment, so every type here carries the type name the Rust side declares with
``#[type_name(...)]`` and the same layout (checked at import).
"""

from __future__ import annotations

import ctypes as C
import math
import enum

import numpy as np

#: Version of the protocol; a server of another version answers VERSION_MISMATCH.
PROTOCOL_VERSION = 12
#: Bytes of a response's status message.
MESSAGE_LEN = 240
#: Request kinds counted in a status report (index = kind code).
KIND_SLOTS = 12
#: Bytes of the map name in a status report.
NAME_LEN = 64
#: Sessions whose gravity pool a status report lists, at most.
STATUS_SESSIONS = 16
#: Floats per IMU sample: seconds after ``imu_t0``, specific force xyz, angular rate xyz.
IMU_SAMPLE_FLOATS = 7

#: View directions follow the points.
FLAG_VIEW_DIRS = 1
#: Packed covariances follow the points (and view directions).
FLAG_COVARIANCES = 2
#: ``stamp`` holds the pose's time.
FLAG_STAMPED = 4
#: Relocalize: the pose guess's rotation gives the sensor's tilt (roll, pitch).
FLAG_LEVELLED = 8
#: Relocalize: answer the search's places unverified (``PLACE_DTYPE`` in the pairings'
#: slots, best first); the first phase over a tile set.
FLAG_PLACES_ONLY = 16
#: Relocalize: settle and score only the places whose ranks are set in
#: ``keyframe_or_scan_id`` (bit r: rank r), answered as ``PLACE_DTYPE``; the second phase.
FLAG_SCORE_CHOSEN = 32
#: Relocalize: the final registration of the scored place whose rank is the one bit set
#: in ``keyframe_or_scan_id`` (found when it fits, no runner-up); the third phase.
FLAG_FINISH_CHOSEN = 64
#: Track: start the session's hosted tracker anew with this scan (relocalizing, or from
#: ``pose`` with ``FLAG_TRACK_FROM_POSE``); the gyro's log is kept.
FLAG_TRACK_RESET = 128
#: Track with ``FLAG_TRACK_RESET``: the tracker starts at ``pose``.
FLAG_TRACK_FROM_POSE = 256
#: ``WireTrack.known`` bits: which optional figures a Track answer holds.
TRACK_EXPLAINED = 1
TRACK_SLIDE_LOSS = 2
TRACK_MAX_CORRECTION = 4
#: ``ResponseHeader.reasons`` of a ``FLAG_PLACES_ONLY`` answer: the places come from the
#: relief search (uphill ground kept), run when the structure search proposed nothing;
#: over a tile set they stand only when no tile proposed from structure.
PLACES_FROM_RELIEF = 1


def rpc_service_name(map_name: str) -> str:
    """The request-response service of a map."""
    return f"kfmap/{map_name}/rpc"


def request_event_name(map_name: str) -> str:
    """The event service clients notify after sending a request."""
    return f"kfmap/{map_name}/request-ready"


def response_event_name(map_name: str) -> str:
    """The event service the server notifies after answering."""
    return f"kfmap/{map_name}/response-ready"


class RequestKind(enum.IntEnum):
    """What a request asks for (``RequestKind`` in Rust)."""

    NEAREST = 1
    RADIUS = 2
    COV2COV = 3
    LOCALIZE = 4
    IMU_WINDOW = 5
    STATUS = 6
    ECHO = 7
    RELOAD = 8
    RELOCALIZE = 9
    TRACK = 10
    TRACK_IMU = 11

    @property
    def label(self) -> str:
        """Lower-case name as the Rust side prints it, e.g. ``"imu-window"``."""
        return self.name.lower().replace("_", "-")


class StatusCode(enum.IntEnum):
    """How a response ended (``StatusCode`` in Rust)."""

    OK = 0
    EMPTY_SCAN = 1
    NON_FINITE_POINT = 2
    TOO_MANY_POINTS = 3
    UNKNOWN_KIND = 4
    MAP_NOT_LOADED = 5
    INTERNAL = 6
    VERSION_MISMATCH = 7
    BAD_REQUEST = 8
    SHUTTING_DOWN = 9
    TOO_LARGE = 10
    BUSY = 11
    NOT_YOUR_SESSION = 12

    @classmethod
    def from_code(cls, code: int) -> "StatusCode":
        """The status of a wire code; unknown codes read as INTERNAL (as in Rust)."""
        try:
            return cls(code)
        except ValueError:
            return cls.INTERNAL

    @property
    def wire_name(self) -> str:
        """The Rust variant name, e.g. ``"TooLarge"``."""
        return "".join(part.capitalize() for part in self.name.split("_"))


class Cov2CovMode(enum.IntEnum):
    """Cov2cov search mode: the map's default, keyframe by keyframe, or merged submap."""

    MAP_DEFAULT = 0
    APPROXIMATE = 1
    EXACT = 2

    @classmethod
    def parse(cls, mode: "Cov2CovMode | str | int") -> "Cov2CovMode":
        """A mode from an enum value, its code or its config name ("map-default", ...)."""
        if isinstance(mode, str):
            key = mode.strip().upper().replace("-", "_")
            if key not in cls.__members__:
                raise ValueError(
                    f"cov2cov mode {mode!r}: use 'map-default', 'approximate' or 'exact'"
                )
            return cls[key]
        return cls(mode)


class TrackingStatus(enum.IntEnum):
    """Localize verdict: OK, DEGRADED (pose adopted, one check marginal), LOST."""

    OK = 0
    DEGRADED = 1
    LOST = 2


class RelocalizeStatus(enum.IntEnum):
    """Relocalize verdict: FOUND, AMBIGUOUS (two places fit alike) or NOT_FOUND."""

    FOUND = 0
    AMBIGUOUS = 1
    NOT_FOUND = 2


#: Bits of a localize answer's ``reasons`` and their names (``tracking::Reasons``).
REASON_NAMES: tuple[tuple[int, str], ...] = (
    (1 << 0, "degenerate"),
    (1 << 1, "not-converged"),
    (1 << 2, "low-fitness"),
    (1 << 3, "no-fit"),
    (1 << 4, "implausible"),
    (1 << 5, "retried"),
    (1 << 6, "ambiguous"),
    (1 << 7, "recovering"),
    (1 << 8, "singular"),
    (1 << 9, "fitness-drop"),
    (1 << 10, "relocalized"),
    (1 << 11, "unfit-streak"),
    (1 << 12, "unpinned"),
)


def reason_names(bits: int) -> list[str]:
    """The names of the reason bits set in ``bits``."""
    return [name for bit, name in REASON_NAMES if bits & bit]


# The structures list their fields in the Rust declaration order; wire.rs documents
# every offset, and the Rust layout test pins them (tests/test_wire.py compares).
u32, u64, f32, f64 = C.c_uint32, C.c_uint64, C.c_float, C.c_double


class RequestHeader(C.Structure):
    """Header of every request (152 bytes); the payload is ``[f32]``."""

    _fields_ = [
        ("version", u32), ("kind", u32), ("request_id", u64), ("client_node", u64 * 2),
        ("pose", f64 * 7), ("point_count", u32), ("flags", u32), ("k", u32), ("mode", u32),
        ("radius", f32), ("max_pair_dist", f32), ("max_iterations", u32),
        ("max_correction", f32), ("keyframe_or_scan_id", u64), ("imu_t0", f64),
        ("expected_inlier_ratio", f32), ("keyframes", u32), ("stamp", f64),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name iceoryx2 compares (Rust: ``#[type_name]``)."""
        return "kfmap::RequestHeader"


def new_request(kind: RequestKind, **fields: object) -> RequestHeader:
    """A request header with the Rust side's defaults (``k`` 1, identity pose)."""
    header = RequestHeader(**{"version": PROTOCOL_VERSION, "kind": kind, "k": 1, **fields})
    header.pose[6] = 1.0
    return header


class WirePairing(C.Structure):
    """One answer element (56 bytes): a map point found for query point ``query``."""

    _fields_ = [
        ("query", u32), ("local_index", u32), ("keyframe", u64), ("point", f32 * 3),
        ("dist_sq", f32), ("information", f32 * 6),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name iceoryx2 compares (Rust: ``#[type_name]``)."""
        return "kfmap::WirePairing"


class WireSessionGravity(C.Structure):
    """One session's gravity pool in a status report (120 bytes)."""

    _fields_ = [
        ("client_node", u64 * 2), ("members", u32), ("compensated", u32), ("pending", u32),
        ("skipped", u32), ("inliers", u32), ("has_gravity", u32), ("bias_observable", u32),
        ("busy", u32), ("roll_pitch", f64 * 2), ("spread_deg", f64), ("accel_bias", f64 * 3),
        ("gravity", f64 * 3),
    ]


class WireCovOptions(C.Structure):
    """The server's covariance options in a status report (40 bytes)."""

    _fields_ = [
        ("k_correspondences", u32), ("min_correspondences", u32), ("center", u32),
        ("reserved", u32), ("max_distance", f64), ("lambda_", f64),
        ("max_plane_deviation", f64),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name in the Rust sources (iceoryx2 checks only the outer header)."""
        return "kfmap::WireCovOptions"


class WireRanking(C.Structure):
    """The server's place-ranking settings in a status report (48 bytes)."""

    _fields_ = [
        ("keep_ratio", f64), ("separation_m", f64), ("separation_deg", f64),
        ("ambiguity_margin", f64), ("distinct_m", f64), ("distinct_deg", f64),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name in the Rust sources (iceoryx2 checks only the outer header)."""
        return "kfmap::WireRanking"


class WireTrack(C.Structure):
    """What a hosted tracker says of a scan beside the localization (104 bytes)."""

    _fields_ = [
        ("predicted", f64 * 7), ("t", f64), ("explained", f64), ("slide_loss", f64),
        ("max_correction", f64), ("hypotheses", u32), ("known", u32), ("imu_refused", u32),
        ("reserved", u32),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name in the Rust sources (iceoryx2 checks only the outer header)."""
        return "kfmap::WireTrack"


class ResponseHeader(C.Structure):
    """Header of every response (3416 bytes); the payload is ``[WirePairing]``."""

    _fields_ = [
        ("version", u32), ("status", u32), ("request_id", u64), ("detail", u64),
        ("message_len", u32), ("active_len", u32), ("active", u64 * 16), ("server_us", f64),
        ("pose", f64 * 7), ("covariance", f64 * 36), ("fitness", f64 * 2), ("iterations", u32),
        ("converged", u32), ("tracking", u32), ("reasons", u32), ("registrations", u32),
        ("degenerate", u32), ("constraint", f64 * 2), ("pose_correction", f64),
        ("relocalization", u32), ("candidates", u32), ("place_scores", f64 * 2),
        ("tight_fitness", f64), ("has_gravity", u32), ("gravity_members", u32),
        ("gravity", f64 * 3), ("roll_pitch", f64 * 2), ("correction", f64 * 4),
        ("gravity_inliers", u32), ("gravity_compensated", u32), ("gravity_pending", u32),
        ("gravity_skipped", u32), ("bias_observable", u32), ("gravity_reserved", u32),
        ("gravity_spread_deg", f64), ("accel_bias", f64 * 3), ("accel_bias_sigma", f64 * 3),
        ("map_keyframes", u64), ("map_points", u64), ("uptime_s", f64),
        ("counts", u64 * KIND_SLOTS), ("p50_us", f32 * KIND_SLOTS),
        ("p99_us", f32 * KIND_SLOTS), ("sessions", u32), ("in_flight", u32),
        ("map_name_len", u32), ("map_name", C.c_uint8 * NAME_LEN),
        ("message", C.c_uint8 * MESSAGE_LEN), ("message_reserved", u32),
        ("session_gravity", WireSessionGravity * STATUS_SESSIONS),
        ("scan_covariance", WireCovOptions),
        ("relocalize_ranking", WireRanking),
        ("track", WireTrack),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name iceoryx2 compares (Rust: ``#[type_name]``)."""
        return "kfmap::ResponseHeader"

    def text(self, field: str, length: int) -> str:
        """A zero-padded UTF-8 text field (lossy on invalid bytes, as in Rust)."""
        raw = bytes(getattr(self, field))
        return raw[: min(length, len(raw))].decode("utf-8", errors="replace")

    @property
    def message_text(self) -> str:
        """The status message (Status answers: the map file's path)."""
        return self.text("message", self.message_len)

    @property
    def map_name_text(self) -> str:
        """The map name of a status report."""
        return self.text("map_name", self.map_name_len)


#: ``WirePairing`` as a numpy structured dtype, for copying answers out in one go.
PAIRING_DTYPE = np.dtype(
    {
        "names": ["query", "local_index", "keyframe", "point", "dist_sq", "information"],
        "formats": ["<u4", "<u4", "<u8", ("<f4", (3,)), "<f4", ("<f4", (6,))],
        "offsets": [0, 4, 8, 16, 28, 32],
        "itemsize": 56,
    }
)

#: A place (``WirePlace``) in a pairing's slot: position (f64), orientation (qx qy qz qw,
#: f32), score (proposed: hit ratio; scored: the verification score) and rank.
PLACE_DTYPE = np.dtype(
    {
        "names": ["translation", "rotation", "score", "rank"],
        "formats": [("<f8", (3,)), ("<f4", (4,)), "<f8", "<u8"],
        "offsets": [0, 24, 40, 48],
        "itemsize": 56,
    }
)


def place_pose(slot: np.void) -> list[float]:
    """The wire pose (x y z qx qy qz qw) of a ``PLACE_DTYPE`` record, its f32 rotation
    renormalized in f64 (as ``kfmap_protocol::place_from_wire``); check it with
    ``geometry.wire_pose_is_valid``."""
    q = [float(v) for v in slot["rotation"]]
    norm = math.sqrt(sum(v * v for v in q))
    return [float(v) for v in slot["translation"]] + [v / norm if norm else v for v in q]


def _check_layouts() -> None:
    """The sizes and a few offsets of ``header_layouts_are_the_documented_ones``."""
    expected = [
        (C.sizeof(RequestHeader), 152),
        (RequestHeader.stamp.offset, 144),
        (RequestHeader.expected_inlier_ratio.offset, 136),
        (RequestHeader.keyframes.offset, 140),
        (C.sizeof(WirePairing), 56),
        (WirePairing.information.offset, 32),
        (C.sizeof(WireSessionGravity), 120),
        (C.sizeof(WireCovOptions), 40),
        (C.sizeof(WireRanking), 48),
        (C.sizeof(WireTrack), 104),
        (WireTrack.hypotheses.offset, 88),
        (C.sizeof(ResponseHeader), 3416),
        (ResponseHeader.track.offset, 3312),
        (ResponseHeader.relocalize_ranking.offset, 3264),
        (ResponseHeader.scan_covariance.offset, 3224),
        (ResponseHeader.p50_us.offset, 888),
        (ResponseHeader.relocalization.offset, 576),
        (ResponseHeader.map_keyframes.offset, 768),
        (ResponseHeader.message.offset, 1060),
        (ResponseHeader.session_gravity.offset, 1304),
        (PAIRING_DTYPE.itemsize, C.sizeof(WirePairing)),
        (PLACE_DTYPE.itemsize, C.sizeof(WirePairing)),
    ]
    for got, want in expected:
        if got != want:  # pragma: no cover - only on a broken platform / edit
            raise ImportError(f"kfmap wire layout mismatch: {got} != {want}")


_check_layouts()
