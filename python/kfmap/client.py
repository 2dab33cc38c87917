"""``kfmap.Client``: the Python counterpart of the Rust ``kfmap_client::Client``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from . import wire
from .errors import InvalidArgument
from .geometry import pose_to_wire
from .results import GravityAnswer, Localized, Pairings, Relocalized, StatusReport, Tracked
from .transport import Connection, Reply


def _rows(name: str, values: npt.ArrayLike, width: int, count: int | None = None) -> np.ndarray:
    """``values`` as a C-contiguous ``(n, width)`` float32 array; float32 or float64
    input only (lists are read as float64). Raises ``InvalidArgument``."""
    if isinstance(values, np.ndarray):
        if values.dtype not in (np.float32, np.float64):
            raise InvalidArgument(f"{name}: dtype {values.dtype} is not float32 or float64")
        a = values
    else:
        try:
            a = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise InvalidArgument(f"{name}: not an array of numbers ({e})") from None
    if a.ndim != 2 or a.shape[1] != width:
        raise InvalidArgument(f"{name}: expected shape (N, {width}), got {a.shape}")
    if count is not None and a.shape[0] != count:
        raise InvalidArgument(f"{name}: {a.shape[0]} rows for {count} points; give one per point")
    if a.shape[0] >= 2**32:
        raise InvalidArgument(f"{name}: too many rows ({a.shape[0]})")
    return np.ascontiguousarray(a, dtype=np.float32)


def _uint(name: str, value: Any, bits: int = 32) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InvalidArgument(f"{name} must be an integer, got {value!r}")
    if not 0 <= int(value) < 2**bits:
        raise InvalidArgument(f"{name} = {value} does not fit an unsigned {bits}-bit integer")
    return int(value)


def _f32(name: str, value: Any, optional: bool = False) -> float:
    if value is None and optional:
        return 0.0
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InvalidArgument(f"{name} must be a number, got {value!r}") from None


def _mode(mode: Any) -> int:
    try:
        return int(wire.Cov2CovMode.parse(mode))
    except ValueError as e:
        raise InvalidArgument(str(e)) from None


def _imu_rows(samples: npt.ArrayLike) -> tuple[np.ndarray, float]:
    """IMU rows ``t ax ay az gx gy gz`` as float64 ``(N, 7)`` and the first time."""
    if isinstance(samples, np.ndarray) and samples.dtype not in (np.float32, np.float64):
        raise InvalidArgument(f"samples: dtype {samples.dtype} is not float32 or float64")
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != wire.IMU_SAMPLE_FLOATS:
        raise InvalidArgument(f"samples: expected shape (N, 7), got {s.shape}")
    t0 = float(s[0, 0]) if len(s) else 0.0
    if not math.isfinite(t0):
        raise InvalidArgument("samples: the first time must be finite")
    return s, t0


def _imu_payload(s: np.ndarray, t0: float) -> np.ndarray:
    """The IMU payload: times after ``t0``, then the six readings, as float32."""
    payload = s.astype(np.float32)
    payload[:, 0] = (s[:, 0] - t0).astype(np.float32)
    return payload.ravel()


def _rotation_pose(rotation: npt.ArrayLike) -> np.ndarray:
    """A pose with no translation and ``rotation`` (3x3 or ``qx qy qz qw``)."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape == (3, 3):
        pose = np.eye(4)
        pose[:3, :3] = r
        return pose
    if r.shape != (4,):
        raise InvalidArgument(f"rotation: expected a 3x3 matrix or qx qy qz qw, got {r.shape}")
    return np.concatenate([np.zeros(3), r])


class Client:
    """A client of the ``kfmap serve`` of one map, over iceoryx2 shared memory.

    Args:
        map_name: the served map's name (``kfmap serve --map-name``).
        iceoryx_prefix: the server's ``--iceoryx-prefix`` (None: iceoryx2's default).
        timeout: longest wait for one answer, seconds. After a timeout (or a server that
            went away) the next call reconnects, so a restarted server is found again.

    Raises:
        NoServerError: no server serves ``map_name`` under this prefix.

    Points are ``(N, 3)`` float32/float64 arrays in the sensor frame (sent as float32);
    poses are 4x4 ``T_map_sensor`` matrices (or ``x y z qx qy qz qw``). Each client is
    one server session (active keyframes, gravity pool). Use it from one thread at a
    time (calls are serialized) and close it (or use ``with``) when done.
    """

    def __init__(
        self, map_name: str, *, iceoryx_prefix: str | None = None, timeout: float = 5.0
    ) -> None:
        self._conn = Connection(map_name, iceoryx_prefix, timeout)

    @classmethod
    def remote(
        cls,
        endpoint: str,
        map_name: str,
        *,
        timeout: float = 5.0,
        zenoh_config: str | None = None,
        client_id: str | None = None,
        tile: str | None = None,
    ) -> "Client":
        """A client of the server of ``map_name`` on another host, through the ``kfmap
        gateway`` at ``endpoint`` (a Zenoh endpoint such as ``tcp/10.0.0.5:7447``; several
        separated by commas): the same calls and errors as a local client. Needs the
        ``eclipse-zenoh`` package (``pip install 'kfmap[remote]'``); ``zenoh_config`` is a
        Zenoh JSON5 file for TLS or mutual TLS.

        A map served in tiles (``kfmap gateway --tiles``, one gateway per host) is found
        by itself (``tile=None``): each request goes to the tile its pose guess routes
        to (staying on a tile within half the halo past its border; see
        :attr:`current_tile`), and ``relocalize`` asks every tile at once. ``tile``
        names one tile (or ``"whole"``) to talk to instead.

        Raises:
            NoServerError: the gateways announce no live server for the map.
            TransportError: no gateway answers at ``endpoint``, or a tile set's index
                cannot be read.
        """
        from .remote import RemoteConnection

        client = cls.__new__(cls)
        client._conn = RemoteConnection(
            map_name, endpoint, timeout, zenoh_config=zenoh_config, client_id=client_id,
            tile=tile,
        )
        return client

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Releases the iceoryx2 ports and node; the server ends the session."""
        self._conn.close()

    @property
    def map_name(self) -> str:
        """The map this client talks to."""
        return self._conn.map_name

    @property
    def timeout(self) -> float:
        """Longest wait for one answer, seconds (settable)."""
        return self._conn.timeout

    @timeout.setter
    def timeout(self, seconds: float) -> None:
        if not seconds > 0:
            raise InvalidArgument(f"timeout {seconds!r} s must be positive")
        self._conn.timeout = float(seconds)

    @property
    def current_tile(self) -> str | None:
        """A remote client's tile: the one the last request went to over a tile set
        (None before the first), else ``"whole"`` or the tile given; None when local."""
        return getattr(self._conn, "current_tile", None)

    @property
    def client_node(self) -> int:
        """This client's iceoryx2 node id, as status reports list sessions."""
        high, low = self._conn.client_node
        return (high << 64) | low

    # -- requests ---------------------------------------------------------------------

    def _scan(
        self,
        kind: wire.RequestKind,
        points: npt.ArrayLike,
        pose: npt.ArrayLike | None,
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
        **fields: Any,
    ) -> Reply:
        """Sends a scan request: points, then view directions and covariances if given."""
        pts = _rows("points", points, 3)
        parts, flags = [pts.ravel()], 0
        if view_dirs is not None:
            parts.append(_rows("view_dirs", view_dirs, 3, len(pts)).ravel())
            flags |= wire.FLAG_VIEW_DIRS
        if covariances is not None:
            parts.append(_rows("covariances", covariances, 6, len(pts)).ravel())
            flags |= wire.FLAG_COVARIANCES
        header = wire.new_request(kind, point_count=len(pts), **fields)
        header.flags |= flags
        header.pose[:] = pose_to_wire(pose)
        return self._conn.call(header, np.concatenate(parts))

    def nearest(
        self,
        points: npt.ArrayLike,
        pose: npt.ArrayLike | None = None,
        *,
        k: int = 1,
        keyframes: int = 0,
        max_dist: float | None = None,
    ) -> Pairings:
        """The ``k`` nearest map points of each scan point (moved by ``pose``), in the
        active keyframes at ``pose``, or with ``keyframes`` (1 to 64) in that many
        keyframes nearest ``pose`` by position: the map around a place whichever way it
        was seen. With ``max_dist`` (metres, up to 20) only the neighbours within it."""
        if max_dist is not None and not 0.0 < _f32("max_dist", max_dist) <= 20.0:
            raise InvalidArgument(f"max_dist must be a distance in (0, 20] m, got {max_dist!r}")
        reply = self._scan(
            wire.RequestKind.NEAREST, points, pose, k=_uint("k", k),
            keyframes=_uint("keyframes", keyframes),
            radius=0.0 if max_dist is None else _f32("max_dist", max_dist),
        )
        return Pairings.from_reply(reply.pairings, reply.header)

    def radius(
        self, points: npt.ArrayLike, pose: npt.ArrayLike | None = None, *, r: float = 0.5
    ) -> Pairings:
        """Every map point within ``r`` metres of each scan point (moved by ``pose``)."""
        reply = self._scan(wire.RequestKind.RADIUS, points, pose, radius=_f32("r", r))
        return Pairings.from_reply(reply.pairings, reply.header)

    def cov2cov(
        self,
        points: npt.ArrayLike,
        pose: npt.ArrayLike | None = None,
        *,
        max_pair_dist: float = 1.0,
        mode: wire.Cov2CovMode | str = "map-default",
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
    ) -> Pairings:
        """GICP pairings of the scan at ``pose`` within ``max_pair_dist`` metres, with
        information matrices. ``covariances`` (N x 6 packed, m^2) default to the
        server's estimate."""
        reply = self._scan(
            wire.RequestKind.COV2COV, points, pose, view_dirs, covariances,
            max_pair_dist=_f32("max_pair_dist", max_pair_dist), mode=_mode(mode),
        )
        return Pairings.from_reply(reply.pairings, reply.header)

    def localize(
        self,
        points: npt.ArrayLike,
        pose_guess: npt.ArrayLike,
        *,
        max_iterations: int = 30,
        max_pair_dist: float = 1.0,
        mode: wire.Cov2CovMode | str = "map-default",
        max_correction: float | None = None,
        expected_inlier_ratio: float | None = None,
        stamp: float | None = None,
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
    ) -> Localized:
        """Server-side localization of a scan from ``pose_guess``.

        ``max_correction``: the largest correction (metres, see the Rust docs) the
        caller's motion model allows (None: no bound). ``expected_inlier_ratio``: the
        inlier ratio of the scans before (None: unknown). ``stamp``: the scan's time on
        the IMU clock, so the session's gravity pool can use the adopted pose. A scan
        that fails the checks comes back ``LOST`` with the guess as its pose.
        """
        correction = _f32("max_correction", max_correction, optional=True)
        expected = _f32("expected_inlier_ratio", expected_inlier_ratio, optional=True)
        fields: dict[str, Any] = dict(
            max_iterations=_uint("max_iterations", max_iterations),
            max_pair_dist=_f32("max_pair_dist", max_pair_dist),
            mode=_mode(mode),
            # As the Rust client: non-positive (or NaN) means none, the ratio at most 1.
            max_correction=correction if correction > 0 else 0.0,
            expected_inlier_ratio=min(expected, 1.0) if expected > 0 else 0.0,
        )
        if stamp is not None:
            fields.update(flags=wire.FLAG_STAMPED, stamp=_f32("stamp", stamp))
        reply = self._scan(
            wire.RequestKind.LOCALIZE, points, pose_guess, view_dirs, covariances, **fields
        )
        return Localized.from_header(reply.header)

    def relocalize(
        self,
        points: npt.ArrayLike,
        *,
        max_pair_dist: float = 1.0,
        max_iterations: int = 30,
        tilt: npt.ArrayLike | None = None,
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
    ) -> Relocalized:
        """Where the scan was taken in the map, with no pose guess.

        ``tilt``: the sensor's roll and pitch (e.g. from an IMU) as a rotation, a 3x3
        matrix or quaternion ``qx qy qz qw`` whose yaw is ignored; None: the server
        finds up in the scan.
        """
        pose = None if tilt is None else _rotation_pose(tilt)
        flags = 0 if tilt is None else wire.FLAG_LEVELLED
        reply = self._scan(
            wire.RequestKind.RELOCALIZE, points, pose, view_dirs, covariances,
            max_pair_dist=_f32("max_pair_dist", max_pair_dist),
            max_iterations=_uint("max_iterations", max_iterations), flags=flags,
        )
        return Relocalized.from_header(reply.header)

    def push_imu_window(
        self,
        keyframe_id: int,
        pose: npt.ArrayLike,
        samples: npt.ArrayLike,
        *,
        stamp: float | None = None,
    ) -> GravityAnswer:
        """Adds the IMU window of keyframe (or scan) ``keyframe_id`` to this session's
        gravity pool and returns the current correction.

        ``samples``: ``(N, 7)`` rows ``t ax ay az gx gy gz`` (seconds, m/s^2, rad/s; as
        a dataset's imu.csv), the time since the previous window. ``pose``: the pose at
        the window's end, taken at ``stamp`` (seconds, the samples' clock); with a stamp
        the server removes the platform's own acceleration once a later stamped pose
        arrives (``pending`` until then), without one the window is pooled as its raw
        mean (right only for a platform at rest).
        """
        s, t0 = _imu_rows(samples)
        header = wire.new_request(
            wire.RequestKind.IMU_WINDOW, point_count=len(s), imu_t0=t0,
            keyframe_or_scan_id=_uint("keyframe_id", keyframe_id, 64),
        )
        if stamp is not None:
            header.flags, header.stamp = wire.FLAG_STAMPED, _f32("stamp", stamp)
        header.pose[:] = pose_to_wire(pose)
        reply = self._conn.call(header, _imu_payload(s, t0))
        return GravityAnswer.from_header(reply.header)

    def track(
        self,
        points: npt.ArrayLike,
        t: float,
        *,
        start: str = "continue",
        pose: npt.ArrayLike | None = None,
        max_iterations: int = 30,
        max_pair_dist: float = 1.0,
        mode: wire.Cov2CovMode | str = "map-default",
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
    ) -> Tracked:
        """One scan through this session's server-hosted tracker (``kfmap.Tracker``
        wraps it). ``t``: the scan's time, seconds on the IMU's clock. ``start``:
        ``"continue"`` (a new session's first scan is relocalized), ``"relocalize"``
        (start anew, no idea where) or ``"pose"`` (start anew at ``pose``). The solver
        options take effect when the tracker starts."""
        t = _f32("t", t)
        if not math.isfinite(t):
            raise InvalidArgument(f"t = {t} is not finite")
        flags = {"continue": 0, "relocalize": wire.FLAG_TRACK_RESET,
                 "pose": wire.FLAG_TRACK_RESET | wire.FLAG_TRACK_FROM_POSE}.get(start)
        if flags is None:
            raise InvalidArgument(f"start = {start!r}: use 'continue', 'relocalize' or 'pose'")
        if (start == "pose") != (pose is not None):
            raise InvalidArgument("give a pose exactly when start = 'pose'")
        reply = self._scan(
            wire.RequestKind.TRACK, points, pose, view_dirs, covariances,
            max_iterations=_uint("max_iterations", max_iterations),
            max_pair_dist=_f32("max_pair_dist", max_pair_dist), mode=_mode(mode),
            flags=flags | wire.FLAG_STAMPED, stamp=t,
        )
        return Tracked.from_reply(reply.header, reply.pairings)

    def push_track_imu(
        self, samples: npt.ArrayLike, *, lidar_from_imu: npt.ArrayLike | None = None
    ) -> int:
        """Gives this session's hosted tracker IMU samples: ``(N, 7)`` rows ``t ax ay az
        gx gy gz`` (seconds on the scans' clock, after those sent before; m/s^2, rad/s).
        ``lidar_from_imu``: the IMU's mounting ``R_lidar_imu`` (3x3 or ``qx qy qz qw``;
        None: aligned). The gyro predicts rotation between scans, the accelerometer
        levels relocalizations. Returns the samples refused (out of order, not finite)."""
        s, t0 = _imu_rows(samples)
        header = wire.new_request(wire.RequestKind.TRACK_IMU, point_count=len(s), imu_t0=t0)
        if lidar_from_imu is not None:
            header.pose[:] = pose_to_wire(_rotation_pose(lidar_from_imu))
        reply = self._conn.call(header, _imu_payload(s, t0))
        return int(reply.header.track.imu_refused)

    def status(self) -> StatusReport:
        """The server's counters: map, sessions, requests per kind, gravity pools."""
        reply = self._conn.call(wire.new_request(wire.RequestKind.STATUS))
        return StatusReport.from_header(reply.header)

    def echo(self, points: npt.ArrayLike) -> int:
        """A round trip with no work; returns the number of points the server got."""
        return int(self._scan(wire.RequestKind.ECHO, points, None).header.detail)

    def reload(self) -> str:
        """Asks the server to reopen its map file; returns its message."""
        return self._conn.call(wire.new_request(wire.RequestKind.RELOAD)).header.message_text

