"""Python client of the kfmap LiDAR keyframe map server.

Talks to a running ``kfmap serve`` over iceoryx2 zero-copy shared memory::

    import kfmap
    with kfmap.Client("site") as client:
        found = client.nearest(points, pose, k=1)
"""

from importlib import metadata as _metadata

from .client import Client
from .errors import (
    DisconnectedError,
    InvalidArgument,
    KfmapError,
    NoServerError,
    RequestTimeout,
    ServerError,
    TooManyClientsError,
    TransportError,
)
from .geometry import pose_from_wire, pose_to_wire
from .results import (
    GravityAnswer,
    Hypothesis,
    KindStats,
    Localized,
    Pairings,
    Relocalized,
    SessionGravity,
    StatusReport,
    Tracked,
)
from .tracker import Tracker
from .wire import (
    PROTOCOL_VERSION,
    Cov2CovMode,
    RelocalizeStatus,
    RequestKind,
    StatusCode,
    TrackingStatus,
)

try:
    __version__ = _metadata.version("kfmap")
except _metadata.PackageNotFoundError:  # imported from a source tree, not installed
    __version__ = "0+unknown"

__all__ = [
    "Client",
    "Cov2CovMode",
    "DisconnectedError",
    "GravityAnswer",
    "Hypothesis",
    "InvalidArgument",
    "KfmapError",
    "KindStats",
    "Localized",
    "NoServerError",
    "PROTOCOL_VERSION",
    "Pairings",
    "RelocalizeStatus",
    "Relocalized",
    "RequestKind",
    "RequestTimeout",
    "ServerError",
    "SessionGravity",
    "StatusCode",
    "StatusReport",
    "Tracked",
    "Tracker",
    "TooManyClientsError",
    "TrackingStatus",
    "TransportError",
    "pose_from_wire",
    "pose_to_wire",
]
