"""What the client returns: small dataclasses with numpy fields, built from a
response header and its pairings (``client/src/lib.rs``, ``localize.rs``,
``relocalize.rs``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import wire
from .errors import KfmapError
from .geometry import pose_from_wire, roll_pitch_quat, wire_pose_is_valid


@dataclass(frozen=True)
class Pairings:
    """Map points found for scan points (nearest, radius, cov2cov), in query order.

    Each array has one entry per pairing; ``query`` indexes the request's points.
    ``information`` is the packed ``(C_map + R C_q R^T)^-1`` (xx xy xz yy yz zz, 1/m^2,
    map frame) for cov2cov and zero otherwise. ``active`` holds the ids of the active
    keyframes the server searched.
    """

    query: np.ndarray  # (n,) uint32
    keyframe: np.ndarray  # (n,) uint64
    local_index: np.ndarray  # (n,) uint32
    point: np.ndarray  # (n, 3) float32, map frame
    dist_sq: np.ndarray  # (n,) float32, m^2
    information: np.ndarray  # (n, 6) float32
    active: np.ndarray  # (m,) uint64

    @classmethod
    def from_reply(cls, records: np.ndarray, header: wire.ResponseHeader) -> "Pairings":
        """Splits ``PAIRING_DTYPE`` records into arrays (each its own contiguous copy)."""
        active = np.array(header.active[: min(header.active_len, 16)], dtype=np.uint64)
        return cls(
            query=np.ascontiguousarray(records["query"]),
            keyframe=np.ascontiguousarray(records["keyframe"]),
            local_index=np.ascontiguousarray(records["local_index"]),
            point=np.ascontiguousarray(records["point"]).reshape(-1, 3),
            dist_sq=np.ascontiguousarray(records["dist_sq"]),
            information=np.ascontiguousarray(records["information"]).reshape(-1, 6),
            active=active,
        )

    def __len__(self) -> int:
        return int(self.query.shape[0])

    def information_matrices(self) -> np.ndarray:
        """The information matrices unpacked to ``(n, 3, 3)`` float64."""
        i = self.information.astype(np.float64)
        xx, xy, xz, yy, yz, zz = (i[:, j] for j in range(6))
        return np.stack(
            [np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)],
            axis=1,
        )


def _checked_pose(values: object) -> np.ndarray:
    if not wire_pose_is_valid(values):
        raise KfmapError("the server sent an invalid pose")
    return pose_from_wire(values)


def _enum(cls: type, code: int, what: str):  # noqa: ANN202 - an IntEnum member
    try:
        return cls(code)
    except ValueError:
        raise KfmapError(f"the server sent an unknown {what} {code}") from None


def _covariance(values: object) -> np.ndarray | None:
    """A 6x6 row-major covariance (rotation first), or None when the server sent zeros."""
    c = np.array(values, dtype=np.float64).reshape(6, 6)
    return c if np.any(c != 0.0) else None


@dataclass(frozen=True)
class Localized:
    """A server-side localized scan: the pose ``T_map_sensor`` and its health.

    When ``status`` is ``LOST`` the pose is the guess (no pose was adopted).
    """

    pose: np.ndarray  # (4, 4)
    status: wire.TrackingStatus
    reasons: int
    inlier_ratio: float
    rmse: float
    rotation_constraint: float
    translation_constraint: float
    degenerate: bool
    covariance: np.ndarray | None  # (6, 6), rotation first, sensor frame
    correction: float
    registrations: int
    iterations: int
    converged: bool
    server_us: float

    @property
    def reason_names(self) -> list[str]:
        """The reason bits by name, e.g. ``["retried", "low-fitness"]``."""
        return wire.reason_names(self.reasons)

    @classmethod
    def from_header(cls, h: wire.ResponseHeader) -> "Localized":
        return cls(
            pose=_checked_pose(h.pose),
            status=_enum(wire.TrackingStatus, h.tracking, "tracking status"),
            reasons=int(h.reasons),
            inlier_ratio=h.fitness[0],
            rmse=h.fitness[1],
            rotation_constraint=h.constraint[0],
            translation_constraint=h.constraint[1],
            degenerate=h.degenerate == 1,
            covariance=_covariance(h.covariance),
            correction=h.pose_correction,
            registrations=int(h.registrations),
            iterations=int(h.iterations),
            converged=h.converged == 1,
            server_us=h.server_us,
        )


@dataclass(frozen=True)
class Hypothesis:
    """A place the sensor may be at while a hosted tracker is in doubt."""

    pose: np.ndarray  # (4, 4) T_map_sensor at the last scan
    explained: float  # mean share of the scans' structure the map explains there
    scans: int  # scans it was compared on


@dataclass(frozen=True)
class Tracked:
    """One scan through the server-hosted tracker (``kfmap.Tracker``): the pose and
    health as ``Localized``, the motion model's ``predicted`` pose, the correction
    bound used, the places in doubt (``hypotheses``, best first; empty while one place
    is tracked) and the trust figures: ``explained`` (share of the scan's structure the
    map explains at the pose; the rest moved since the map) and ``slide_loss`` (what a
    0.5 m slide along the least constrained direction loses of it). ``None``: not
    measured (e.g. when ``LOST``)."""

    t: float
    localized: Localized
    predicted: np.ndarray  # (4, 4)
    max_correction: float | None
    hypotheses: list[Hypothesis]
    explained: float | None
    slide_loss: float | None

    @property
    def pose(self) -> np.ndarray:
        """``T_map_sensor`` (the prediction when ``LOST``)."""
        return self.localized.pose

    @property
    def status(self) -> wire.TrackingStatus:
        """OK, DEGRADED or LOST."""
        return self.localized.status

    @property
    def reason_names(self) -> list[str]:
        """Why the status is not OK, e.g. ``["ambiguous"]``."""
        return self.localized.reason_names

    @classmethod
    def from_reply(cls, h: wire.ResponseHeader, places: np.ndarray) -> "Tracked":
        tr = h.track
        if len(places) != tr.hypotheses:
            raise KfmapError(f"the server sent {len(places)} places for {tr.hypotheses} hypotheses")
        records = places.view(wire.PLACE_DTYPE) if len(places) else places
        hypotheses = []
        for rec in records:
            hypotheses.append(Hypothesis(_checked_pose(wire.place_pose(rec)), float(rec["score"]),
                                         int(rec["rank"])))

        def figure(value: float, bit: int) -> float | None:
            return float(value) if tr.known & bit else None

        return cls(
            t=tr.t,
            localized=Localized.from_header(h),
            predicted=_checked_pose(tr.predicted),
            max_correction=figure(tr.max_correction, wire.TRACK_MAX_CORRECTION),
            hypotheses=hypotheses,
            explained=figure(tr.explained, wire.TRACK_EXPLAINED),
            slide_loss=figure(tr.slide_loss, wire.TRACK_SLIDE_LOSS),
        )


@dataclass(frozen=True)
class Relocalized:
    """Where the server placed a scan with no guess; ``pose`` is None when NOT_FOUND."""

    status: wire.RelocalizeStatus
    pose: np.ndarray | None  # (4, 4)
    inlier_ratio: float
    rmse: float
    tight_inlier_ratio: float
    degenerate: bool
    converged: bool
    score: float
    runner_up: float
    candidates: int
    covariance: np.ndarray | None
    server_us: float

    @classmethod
    def from_header(cls, h: wire.ResponseHeader) -> "Relocalized":
        status = _enum(wire.RelocalizeStatus, h.relocalization, "relocalization status")
        found = status != wire.RelocalizeStatus.NOT_FOUND
        pose = _checked_pose(h.pose) if found else None
        return cls(
            status=status,
            pose=pose,
            inlier_ratio=h.fitness[0],
            rmse=h.fitness[1],
            tight_inlier_ratio=h.tight_fitness,
            degenerate=h.degenerate == 1,
            converged=h.converged == 1,
            score=h.place_scores[0],
            runner_up=h.place_scores[1],
            candidates=int(h.candidates),
            covariance=_covariance(h.covariance),
            server_us=h.server_us,
        )


@dataclass(frozen=True)
class GravityAnswer:
    """A session's gravity pool and its correction (``push_imu_window``, status)."""

    members: int
    gravity: np.ndarray | None  # (3,) map frame, m/s^2; None while too few members
    roll_pitch: np.ndarray  # (2,) radians
    correction: np.ndarray  # (4,) quaternion qx qy qz qw
    inliers: int
    compensated: int
    pending: int
    skipped: int
    spread_deg: float
    accel_bias: np.ndarray  # (3,) body frame, m/s^2
    accel_bias_sigma: np.ndarray | None  # (3,), None when unknown
    bias_observable: bool

    @property
    def fully_compensated(self) -> bool:
        """True when every pooled member was motion-compensated (and there are members)."""
        return self.members > 0 and self.compensated == self.members

    @classmethod
    def from_header(cls, h: wire.ResponseHeader) -> "GravityAnswer":
        has = h.has_gravity == 1
        sigma = np.array(h.accel_bias_sigma, dtype=np.float64)
        return cls(
            members=int(h.gravity_members),
            gravity=np.array(h.gravity, dtype=np.float64) if has else None,
            roll_pitch=np.array(h.roll_pitch, dtype=np.float64),
            correction=np.array(h.correction, dtype=np.float64),
            inliers=int(h.gravity_inliers),
            compensated=int(h.gravity_compensated),
            pending=int(h.gravity_pending),
            skipped=int(h.gravity_skipped),
            spread_deg=h.gravity_spread_deg,
            accel_bias=np.array(h.accel_bias, dtype=np.float64),
            accel_bias_sigma=sigma if has and np.any(sigma != 0.0) else None,
            bias_observable=h.bias_observable == 1,
        )

    @classmethod
    def from_session(cls, g: wire.WireSessionGravity) -> "GravityAnswer":
        """A pool as a status report lists it (no sigma there)."""
        roll, pitch = g.roll_pitch
        return cls(
            members=int(g.members),
            gravity=np.array(g.gravity, dtype=np.float64) if g.has_gravity == 1 else None,
            roll_pitch=np.array(g.roll_pitch, dtype=np.float64),
            correction=roll_pitch_quat(roll, pitch),
            inliers=int(g.inliers),
            compensated=int(g.compensated),
            pending=int(g.pending),
            skipped=int(g.skipped),
            spread_deg=g.spread_deg,
            accel_bias=np.array(g.accel_bias, dtype=np.float64),
            accel_bias_sigma=None,
            bias_observable=g.bias_observable == 1,
        )


@dataclass(frozen=True)
class SessionGravity:
    """One session's gravity pool in a status report."""

    client: int  # the session's client node id (128 bits)
    busy: bool  # it was answering a request and was not read (pool empty)
    pool: GravityAnswer


@dataclass(frozen=True)
class KindStats:
    """Requests of one kind the server answered, with latency percentiles."""

    count: int
    p50_us: float
    p99_us: float


@dataclass(frozen=True)
class StatusReport:
    """The server's counters (``kfmap status``)."""

    map_name: str
    map_path: str
    keyframes: int
    points: int
    uptime_s: float
    sessions: int
    in_flight: int
    kinds: dict[str, KindStats] = field(default_factory=dict)  # by label, count > 0
    map_from_input: np.ndarray = field(default_factory=lambda: np.eye(4))
    session_gravity: list[SessionGravity] = field(default_factory=list)

    @classmethod
    def from_header(cls, h: wire.ResponseHeader) -> "StatusReport":
        kinds = {
            k.label: KindStats(int(h.counts[k]), float(h.p50_us[k]), float(h.p99_us[k]))
            for k in wire.RequestKind
            if k < wire.KIND_SLOTS and h.counts[k] > 0
        }
        sessions = [
            SessionGravity(
                client=(g.client_node[0] << 64) | g.client_node[1],
                busy=g.busy == 1,
                pool=GravityAnswer.from_session(g),
            )
            for g in list(h.session_gravity)[: min(h.sessions, wire.STATUS_SESSIONS)]
        ]
        return cls(
            map_name=h.map_name_text,
            map_path=h.message_text,
            keyframes=int(h.map_keyframes),
            points=int(h.map_points),
            uptime_s=h.uptime_s,
            sessions=int(h.sessions),
            in_flight=int(h.in_flight),
            kinds=kinds,
            map_from_input=pose_from_wire(h.pose) if wire_pose_is_valid(h.pose) else np.eye(4),
            session_gravity=sessions,
        )
