"""The remote side of a connection: requests as Zenoh queries to a ``kfmap gateway`` on
another host, which answers them through its local server (``client/src/remote.rs``).

A frame is the request's header bytes followed by its float32 payload; the answer is
the response header's bytes followed by its pairings (docs/PROTOCOL.md, "Remote
frames"). Needs the ``eclipse-zenoh`` package (``pip install kfmap[remote]``).
"""

from __future__ import annotations

import ctypes as C
import json
import os
import threading
import time

import numpy as np

from . import wire
from .errors import (
    DisconnectedError,
    InvalidArgument,
    NoServerError,
    RequestTimeout,
    ServerError,
    TransportError,
)
from .transport import Reply

#: The tile chunk of a map served whole.
WHOLE_MAP_TILE = "whole"
#: How often a pending answer checks the tile's liveliness token, seconds.
WATCH_SLICE_S = 0.002
#: Longest wait for the gateway's token when connecting, seconds.
CONNECT_WAIT_S = 2.0


def _zenoh():
    try:
        import zenoh
    except ImportError:
        raise TransportError(
            "remote clients need the eclipse-zenoh package: pip install 'kfmap[remote]'"
        ) from None
    return zenoh


def _check_chunk(what: str, name: str) -> None:
    if not isinstance(name, str) or not name or any(c in name for c in "/*$?#"):
        raise InvalidArgument(
            f"{what} {name!r} cannot be a Zenoh key chunk: it must be non-empty, "
            "without '/', '*', '$', '?' or '#'"
        )


def _prefix(map_name: str) -> str:
    return f"kfmap/{map_name}/v{wire.PROTOCOL_VERSION}"


def _failure(text: str, map_name: str, timeout: float) -> Exception:
    """The exception an error reply ``"<code>: <message>"`` of a gateway stands for."""
    code, _, message = text.partition(": ")
    if code == "no-server":
        return NoServerError(map_name)
    if code == "disconnected":
        return DisconnectedError(map_name)
    if code == "timeout":
        return RequestTimeout(map_name, timeout)
    return TransportError(f"the gateway of {map_name} failed: {message or text}")


class RemoteConnection:
    """A connection to the server of one map on another host, through its gateway.
    Calls are serialized by a lock, as on :class:`kfmap.transport.Connection`."""

    def __init__(
        self,
        map_name: str,
        endpoint: str,
        timeout: float,
        *,
        zenoh_config: str | os.PathLike | None = None,
        client_id: str | None = None,
        tile: str = WHOLE_MAP_TILE,
    ) -> None:
        zenoh = _zenoh()
        _check_chunk("map name", map_name)
        _check_chunk("tile", tile)
        if client_id is None:
            client_id = f"py{os.getpid():x}-{time.time_ns():x}"
        _check_chunk("client id", client_id)
        if not timeout > 0:
            raise InvalidArgument(f"timeout {timeout!r} s must be positive")
        endpoints = [e.strip() for e in (endpoint or "").split(",") if e.strip()]
        if not endpoints and zenoh_config is None:
            raise InvalidArgument("a remote client needs a gateway endpoint, e.g. tcp/10.0.0.5:7447")
        self.map_name = map_name
        self.timeout = float(timeout)
        self.client_node = (0, 0)  # the gateway gives each remote client its own session
        self._lock = threading.Lock()
        self._next_request_id = 1
        config = zenoh.Config.from_file(os.fspath(zenoh_config)) if zenoh_config else zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        if zenoh_config is None:
            config.insert_json5("listen/endpoints", "[]")
        if endpoints:
            config.insert_json5("connect/endpoints", json.dumps(endpoints))
            config.insert_json5("connect/exit_on_failure", "true")
            config.insert_json5("connect/timeout_ms", "3000")
        try:
            self._session = zenoh.open(config)
        except Exception as e:
            raise TransportError(f"connect to the gateway at {', '.join(endpoints)}: {e}") from e
        self._key = f"{_prefix(map_name)}/{tile}/rpc/{client_id}"
        token = f"{_prefix(map_name)}/{tile}/alive"
        self._alive = threading.Event()

        def on_token(sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.set()
            else:
                self._alive.clear()

        self._watch = self._session.liveliness().declare_subscriber(
            token, on_token, history=True
        )
        # The tokens alive now; the subscriber keeps the flag current after.
        for reply in self._session.liveliness().get(token, timeout=CONNECT_WAIT_S):
            if reply.ok is not None:
                self._alive.set()
        if not self._alive.is_set():
            self.close()
            raise NoServerError(f"{map_name} (tile {tile} at {', '.join(endpoints)})")

    def reconnect(self) -> None:
        """Nothing to rebuild: Zenoh reconnects by itself."""

    def close(self) -> None:
        """Closes the Zenoh session (idempotent); the gateway ends the server session
        after its idle time."""
        session, self._session = getattr(self, "_session", None), None
        if session is not None:
            try:
                session.close()
            except Exception:
                pass

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._session is None

    def call(self, header: wire.RequestHeader, payload: np.ndarray | None = None) -> Reply:
        """Sends ``header`` with ``payload`` (float32, flat) and waits for the answer.
        Error statuses raise ``ServerError``."""
        zenoh = _zenoh()
        with self._lock:
            if self._session is None:
                raise TransportError("the client is closed")
            if not self._alive.is_set():
                raise NoServerError(self.map_name)
            header.version = wire.PROTOCOL_VERSION
            header.client_node[0], header.client_node[1] = self.client_node
            header.request_id = self._next_request_id
            self._next_request_id += 1
            frame = bytes(C.string_at(C.byref(header), C.sizeof(header)))
            if payload is not None and payload.size:
                frame += np.ascontiguousarray(payload, dtype="<f4").tobytes()
            answers: list = []
            done = threading.Event()

            def on_reply(reply) -> None:
                answers.append(reply)
                done.set()

            self._session.get(
                self._key,
                zenoh.handlers.Callback(on_reply, done.set),
                payload=frame,
                target=zenoh.QueryTarget.BEST_MATCHING,
                timeout=self.timeout,
            )
            deadline = time.monotonic() + self.timeout
            while not done.wait(WATCH_SLICE_S):
                if not self._alive.is_set():
                    raise DisconnectedError(self.map_name)
                if time.monotonic() >= deadline:
                    raise RequestTimeout(self.map_name, self.timeout)
            if not answers:
                # The query ended with no answer: the gateway's session closed.
                raise DisconnectedError(self.map_name)
            reply = answers[0]
            if reply.ok is None:
                raise _failure(reply.err.payload.to_string(), self.map_name, self.timeout)
            return _decode_answer(reply.ok.payload.to_bytes())


def _decode_answer(frame: bytes) -> Reply:
    head = C.sizeof(wire.ResponseHeader)
    item = wire.PAIRING_DTYPE.itemsize
    if len(frame) < head or (len(frame) - head) % item:
        raise TransportError(f"the gateway sent a broken answer frame of {len(frame)} bytes")
    header = wire.ResponseHeader.from_buffer_copy(frame[:head])
    if header.status != wire.StatusCode.OK:
        raise ServerError(header.status, header.message_text, header.detail)
    pairings = np.frombuffer(frame, dtype=wire.PAIRING_DTYPE, offset=head).copy()
    return Reply(header, pairings)
