"""Exceptions raised by the kfmap client.

Every exception derives from :class:`KfmapError`, so ``except kfmap.KfmapError``
catches everything this package raises on purpose.
"""

from __future__ import annotations

from .wire import StatusCode


class KfmapError(Exception):
    """Base class of every kfmap client error."""


class InvalidArgument(KfmapError, ValueError):
    """A call's argument has the wrong shape, dtype or value; nothing was sent."""


class TransportError(KfmapError):
    """iceoryx2 refused a step (node, service, port, loan or send)."""


class NoServerError(KfmapError):
    """No server serves this map name under this iceoryx2 prefix."""

    def __init__(self, map_name: str) -> None:
        super().__init__(
            f"no kfmap server serves map {map_name!r}; start one with "
            f"`kfmap serve --map FILE --map-name {map_name}` (same --iceoryx-prefix)"
        )
        self.map_name = map_name


class TooManyClientsError(KfmapError):
    """This process already holds the most client ports one process may open."""


class RequestTimeout(KfmapError, TimeoutError):
    """No answer within the timeout; the next call reconnects."""

    def __init__(self, map_name: str, waited: float) -> None:
        super().__init__(
            f"no answer from the server of map {map_name!r} within {waited:g} s; "
            "it may have died (the next call reconnects)"
        )
        self.map_name = map_name
        self.waited = waited


class DisconnectedError(KfmapError):
    """The server stopped (or was replaced) before answering; the next call reconnects."""

    def __init__(self, map_name: str) -> None:
        super().__init__(
            f"the server of map {map_name!r} stopped before answering "
            "(shut down or restarted); the next call reconnects"
        )
        self.map_name = map_name


class ServerError(KfmapError):
    """The server answered with an error status.

    Attributes:
        status: the :class:`~kfmap.wire.StatusCode` (an ``IntEnum``; its int value is
            the wire code).
        message: the server's message, naming the problem.
        detail: extra information, e.g. the index of the first non-finite point.
    """

    def __init__(self, status: int, message: str, detail: int = 0) -> None:
        self.status = StatusCode.from_code(status)
        self.code = int(status)
        self.message = message
        self.detail = detail
        super().__init__(
            f"server refused the request ({self.status.wire_name}, status {self.code}): {message}"
        )

    @property
    def status_name(self) -> str:
        """The status as the Rust side names it, e.g. ``"TooLarge"``."""
        return self.status.wire_name
