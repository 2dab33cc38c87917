"""``kfmap.Tracker``: follows a sensor through its scans with the tracker the server
hosts for the client's session: the same code as ``kfmap localize`` and the ROS 2
node (motion model and gyro prediction, the correction gate, hypotheses across scans
when a place is ambiguous, the trust checks), so a Python process gets the same poses
and statuses without running any of it (docs/DESIGN.md#hosted-tracking)."""

from __future__ import annotations

import numpy.typing as npt

from . import wire
from .results import Tracked


class Tracker:
    """Tracks scans through ``client``'s server-hosted tracker.

    Args:
        client: a ``kfmap.Client``; its session holds the one tracker (use one
            ``Tracker`` per client).
        initial: where the first scan was taken, ``T_map_sensor`` (4x4 or ``x y z qx
            qy qz qw``); None: the first scan is relocalized, with the map's doubts
            kept as hypotheses until one place wins.
        lidar_from_imu: the IMU's mounting ``R_lidar_imu`` for ``push_imu``.
        max_iterations, max_pair_dist, mode: the registration's, as ``localize``.

    A pose whose status is ``OK`` is the tracker's promise that it is right (within
    0.5 m and 5 deg); while places are in doubt the status is ``LOST`` with the reason
    ``ambiguous`` and ``Tracked.hypotheses`` lists them.
    """

    def __init__(
        self,
        client: "kfmap.Client",  # noqa: F821 - the package's own Client
        *,
        initial: npt.ArrayLike | None = None,
        lidar_from_imu: npt.ArrayLike | None = None,
        max_iterations: int = 30,
        max_pair_dist: float = 1.0,
        mode: wire.Cov2CovMode | str = "map-default",
    ) -> None:
        self._client = client
        self._lidar_from_imu = lidar_from_imu
        self._solver = dict(max_iterations=max_iterations, max_pair_dist=max_pair_dist,
                            mode=mode)
        self.reset(initial)

    def reset(self, initial: npt.ArrayLike | None = None) -> None:
        """Starts anew with the next scan: at ``initial``, or relocalizing it. The IMU
        samples given so far are kept."""
        self._start = "relocalize" if initial is None else "pose"
        self._initial = initial

    def push_imu(self, samples: npt.ArrayLike) -> int:
        """IMU rows ``t ax ay az gx gy gz`` (seconds on the scans' clock, in time order
        after those before; m/s^2, rad/s). Returns the samples refused."""
        return self._client.push_track_imu(samples, lidar_from_imu=self._lidar_from_imu)

    def track(
        self,
        points: npt.ArrayLike,
        t: float,
        *,
        view_dirs: npt.ArrayLike | None = None,
        covariances: npt.ArrayLike | None = None,
    ) -> Tracked:
        """Localizes the scan ``points`` (``(N, 3)``, sensor frame, deskewed), taken at
        ``t`` seconds, and updates the tracker."""
        tracked = self._client.track(
            points, t, start=self._start, pose=self._initial, view_dirs=view_dirs,
            covariances=covariances, **self._solver,
        )
        self._start, self._initial = "continue", None
        return tracked
