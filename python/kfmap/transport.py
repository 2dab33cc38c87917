"""The iceoryx2 side of a connection: the map's services opened with the settings the
server uses (``protocol/src/transport.rs``), one request at a time with a
timeout, and reconnection after a timeout (``client/src/connection.rs``).
"""

from __future__ import annotations

import ctypes as C
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import iceoryx2 as iox2
import numpy as np

from . import wire
from .errors import (
    DisconnectedError,
    InvalidArgument,
    NoServerError,
    RequestTimeout,
    ServerError,
    TooManyClientsError,
    TransportError,
)

#: Client ports a map's services admit, over all processes.
MAX_CLIENTS = 128
#: Client ports one process may open (the server's default max-clients-per-process).
MAX_CLIENTS_PER_PROCESS = 16
#: Slice length (floats) reserved for a first request; larger ones grow the segment.
INITIAL_SLICE_LEN = 16 * 1024
#: Longest single sleep on the response event while waiting, seconds.
WAIT_SLICE_S = 0.05
#: The node name of every kfmap client.
NODE_NAME = "kfmap-client"

# Client ports open in this process, per (prefix, map name): the Rust library's
# per-process limit, counted here as iceoryx2's Python binding cannot list clients.
_open_ports: dict[tuple[str | None, str], int] = {}
_open_ports_lock = threading.Lock()


@dataclass
class Reply:
    """An answer copied out of shared memory (status already checked: OK)."""

    header: wire.ResponseHeader
    pairings: np.ndarray  # PAIRING_DTYPE records


def _iox(what: str, call: Callable[[], Any]) -> Any:
    """Runs an iceoryx2 step, turning its exceptions into ``TransportError``."""
    try:
        return call()
    except Exception as e:  # the binding's errors derive from Exception only
        raise TransportError(f"iceoryx2: {what}: {type(e).__name__}: {e}") from e


def _service_name(name: str, map_name: str) -> Any:
    try:
        return iox2.ServiceName.new(name)
    except Exception:
        raise InvalidArgument(
            f"map name {map_name!r} cannot be used in an iceoryx2 service name"
        ) from None


class Connection:
    """A connection to the server of one map: iceoryx2 node, ports, request ids. Calls
    are serialized by a lock (one request in flight, as the service allows)."""

    def __init__(self, map_name: str, iceoryx_prefix: str | None, timeout: float) -> None:
        if not isinstance(map_name, str) or not map_name:
            raise InvalidArgument("map_name must be a non-empty string")
        if not timeout > 0:
            raise InvalidArgument(f"timeout {timeout!r} s must be positive")
        self.map_name = map_name
        self.prefix = iceoryx_prefix
        self.timeout = float(timeout)
        self._lock = threading.Lock()
        self._ports: dict[str, Any] | None = None
        self._next_request_id = 1
        config = iox2.config.default()
        if iceoryx_prefix is not None:
            try:
                config.global_cfg.prefix = iox2.FileName.new(iceoryx_prefix)
            except Exception:
                raise InvalidArgument(
                    f"iceoryx2 prefix {iceoryx_prefix!r} is not a valid file name "
                    "(letters, digits, '-', '_', '.')"
                ) from None
        self._node = _iox(
            "create node",
            lambda: iox2.NodeBuilder.new()
            .config(config)
            .name(iox2.NodeName.new(NODE_NAME))
            .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
            .create(iox2.ServiceType.Ipc),
        )
        node_id = int(self._node.id.value)
        #: This client's node id as written into every request (high word first).
        self.client_node = (node_id >> 64, node_id & 0xFFFF_FFFF_FFFF_FFFF)
        try:
            rpc = self._open_ports()["services"][0]
            if rpc.dynamic_config.number_of_servers == 0:
                raise NoServerError(map_name)
        except BaseException:
            self.close()
            raise

    # -- services and ports ---------------------------------------------------------

    def _rpc_service(self) -> Any:
        # The settings of transport.rs `open_rpc`: whoever arrives first creates the
        # service with them, and iceoryx2 refuses to open it with incompatible ones.
        name = _service_name(wire.rpc_service_name(self.map_name), self.map_name)
        return _iox(
            "open the request-response service",
            lambda: self._node.service_builder(name)
            .request_response(iox2.Slice[C.c_float], iox2.Slice[wire.WirePairing])
            .request_header(wire.RequestHeader)
            .response_header(wire.ResponseHeader)
            .max_servers(1)
            .max_clients(MAX_CLIENTS)
            .max_nodes(MAX_CLIENTS + 2)
            .max_active_requests_per_client(1)
            .max_response_buffer_size(1)
            .max_borrowed_responses_per_pending_response(1)
            .open_or_create(),
        )

    def _event_service(self, name: str) -> Any:
        service_name = _service_name(name, self.map_name)
        return _iox(
            "open an event service",
            lambda: self._node.service_builder(service_name)
            .event()
            .max_listeners(MAX_CLIENTS + 2)
            .max_notifiers(MAX_CLIENTS + 2)
            .max_nodes(MAX_CLIENTS + 2)
            .open_or_create(),
        )

    def _open_ports(self) -> dict[str, Any]:
        if self._ports is not None:
            return self._ports
        key = (self.prefix, self.map_name)
        with _open_ports_lock:
            if _open_ports.get(key, 0) >= MAX_CLIENTS_PER_PROCESS:
                raise TooManyClientsError(
                    f"this process already has {MAX_CLIENTS_PER_PROCESS} kfmap clients of "
                    f"map {self.map_name!r} open, the most one process may; close clients "
                    "it no longer uses"
                )
            _open_ports[key] = _open_ports.get(key, 0) + 1
        try:
            rpc = self._rpc_service()
            requests = self._event_service(wire.request_event_name(self.map_name))
            responses = self._event_service(wire.response_event_name(self.map_name))
            self._ports = {
                "services": (rpc, requests, responses),
                "client": _iox(
                    "create the client port",
                    lambda: rpc.client_builder()
                    .initial_max_slice_len(INITIAL_SLICE_LEN)
                    .allocation_strategy(iox2.AllocationStrategy.PowerOfTwo)
                    .create(),
                ),
                "notifier": _iox(
                    "create the request notifier", lambda: requests.notifier_builder().create()
                ),
                "listener": _iox(
                    "create the response listener",
                    lambda: responses.listener_builder().create(),
                ),
            }
        except BaseException:
            self._release_count()
            raise
        return self._ports

    def _release_count(self) -> None:
        key = (self.prefix, self.map_name)
        with _open_ports_lock:
            _open_ports[key] = max(0, _open_ports.get(key, 0) - 1)
            if not _open_ports[key]:
                del _open_ports[key]

    def _drop_ports(self) -> None:
        ports, self._ports = self._ports, None
        if ports is None:
            return
        for name in ("client", "notifier", "listener"):
            try:
                ports[name].delete()
            except Exception:
                pass
        ports.clear()
        self._release_count()

    def reconnect(self) -> None:
        """Cleans up dead nodes (e.g. a killed server); ports are rebuilt on next use."""
        self._drop_ports()
        try:
            self._node.try_cleanup_dead_nodes()
        except Exception:
            pass

    def close(self) -> None:
        """Releases the ports and the node (idempotent)."""
        self._drop_ports()
        self._node = None

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._node is None

    # -- one request ----------------------------------------------------------------

    def call(self, header: wire.RequestHeader, payload: np.ndarray | None = None) -> Reply:
        """Sends ``header`` with ``payload`` (float32, C-contiguous, flat) and waits for
        the answer. Error statuses raise ``ServerError``."""
        with self._lock:
            if self._node is None:
                raise TransportError("the client is closed")
            floats = 0 if payload is None else int(payload.size)
            header.version = wire.PROTOCOL_VERSION
            header.client_node[0], header.client_node[1] = self.client_node
            header.request_id = self._next_request_id
            self._next_request_id += 1
            ports = self._open_ports()
            request = _iox("loan a request", lambda: ports["client"].loan_slice_uninit(floats))
            C.memmove(request.user_header_ptr, C.byref(header), C.sizeof(header))
            if floats:
                dst = (C.c_float * floats).from_address(request.payload_ptr)
                np.frombuffer(dst, dtype=np.float32)[:] = payload
            pending = _iox("send a request", lambda: request.assume_init().send())
            try:
                ports["notifier"].notify()
            except Exception:
                pass  # the server also polls; a lost wake-up costs latency only
            lost = False
            try:
                return self._wait(pending, ports["listener"])
            except (DisconnectedError, RequestTimeout):
                lost = True
                raise
            finally:
                try:
                    pending.delete()
                except Exception:
                    pass
                if lost:
                    # The pending request goes before the port it belongs to, as in the
                    # Rust client; the next call finds a restarted server.
                    self.reconnect()

    def _wait(self, pending: Any, listener: Any) -> Reply:
        deadline = time.monotonic() + self.timeout
        while True:
            # Read before asking whether the server is still there: it lets go of the
            # request right after answering.
            gone = not pending.is_connected
            response = _iox("receive a response", pending.receive)
            if response is not None:
                try:
                    return _copy_out(response)
                finally:
                    response.delete()
            if gone:
                raise DisconnectedError(self.map_name)
            left = deadline - time.monotonic()
            if left <= 0:
                raise RequestTimeout(self.map_name, self.timeout)
            wait = iox2.Duration.from_secs_f64(min(left, WAIT_SLICE_S))
            try:
                listener.timed_wait(wait)
            except Exception:
                time.sleep(min(left, 0.001))


def _copy_out(response: Any) -> Reply:
    """Copies an answer out of shared memory, raising ``ServerError`` on a bad status."""
    header = wire.ResponseHeader.from_buffer_copy(
        C.string_at(response.user_header_ptr, C.sizeof(wire.ResponseHeader))
    )
    if header.status != wire.StatusCode.OK:
        raise ServerError(header.status, header.message_text, header.detail)
    # `header.number_of_elements` counts pairings; the binding's Slice.len() is bytes.
    count = int(response.header.number_of_elements)
    if count:
        raw = (C.c_uint8 * (count * wire.PAIRING_DTYPE.itemsize)).from_address(
            response.payload_ptr
        )
        pairings = np.frombuffer(raw, dtype=wire.PAIRING_DTYPE, count=count).copy()
    else:
        pairings = np.empty(0, dtype=wire.PAIRING_DTYPE)
    return Reply(header=header, pairings=pairings)
