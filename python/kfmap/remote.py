"""The remote side of a connection: requests as Zenoh queries to the ``kfmap gateway`` of
each host, which answers them through its local server (``client/src/remote.rs``).

A frame is the request's header bytes followed by its float32 payload; the answer is
the response header's bytes followed by its pairings (docs/PROTOCOL.md, "Remote
frames"). A map served in tiles (``kfmap bake --tile-size``, docs/DESIGN.md#notes-tiles)
is learned from a gateway's tile index: each request goes to the tile its pose guess
routes to (:class:`TileRouter`), and a relocalization goes to every tile at once, the
answers ranked as one search over the whole map (:func:`merge_relocalizations`). Needs
the ``eclipse-zenoh`` package (``pip install kfmap[remote]``).
"""

from __future__ import annotations

import ctypes as C
import json
import math
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

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
from .geometry import wire_pose_is_valid
from .transport import Reply

#: The tile chunk of a map served whole.
WHOLE_MAP_TILE = "whole"
#: How often a pending answer checks the tile's liveliness token, seconds.
WATCH_SLICE_S = 0.002
#: Longest wait for the gateway's token (and a tile set's index) when connecting, seconds.
CONNECT_WAIT_S = 2.0
#: Pause between two asks for a tile set's index, seconds.
INDEX_RETRY_S = 0.02
#: The tile index format this client reads (``tiles.toml``'s ``format``).
INDEX_FORMAT = 1
#: Relocalization merging (``RelocalizeParams`` defaults): a runner-up within this score
#: of the best makes the answer ambiguous ...
AMBIGUITY_MARGIN = 0.05
#: ... if its place is farther than this from the best's (metres) ...
DISTINCT_M = 1.0
#: ... or turned more than this (degrees).
DISTINCT_DEG = 5.0

#: :meth:`TileRouter.route` outcomes: to a tile, the owner tile down, no tile up.
ROUTE_TILE, ROUTE_DOWN, ROUTE_NONE_UP = "tile", "down", "none-up"


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


def _tile_of_key(map_name: str, key: str, suffix: str) -> str | None:
    """The tile chunk of ``kfmap/<map>/v<P>/<tile><suffix>...`` keys of ``map_name``."""
    head = f"{_prefix(map_name)}/"
    if not key.startswith(head):
        return None
    tile, found, _ = key[len(head):].partition(suffix)
    return tile if found and tile and "/" not in tile else None


def _tile_of_alive_key(map_name: str, key: str) -> str | None:
    tile = _tile_of_key(map_name, key, "/alive")
    return tile if tile is not None and key.endswith("/alive") else None


def _tile_of_rpc_key(map_name: str, key: str) -> str | None:
    return _tile_of_key(map_name, key, "/rpc/")


# -- tile sets ------------------------------------------------------------------------


def tile_id(col: int, row: int) -> str:
    """A tile's id: ``x<col>_y<row>``."""
    return f"x{col}_y{row}"


@dataclass(frozen=True)
class TileEntry:
    """One tile of a tile set's index: id and grid cell."""

    id: str
    col: int
    row: int


@dataclass(frozen=True)
class TileIndex:
    """A tile set's index (``tiles.toml``, format 1) as far as routing needs it: tile
    ``(col, row)``'s core square is ``[col s, (col+1) s) x [row s, (row+1) s)`` for
    ``s = tile_size``; its file also holds every keyframe within ``halo`` of it."""

    tile_size: float
    halo: float
    keyframes: int
    tiles: tuple[TileEntry, ...]

    @classmethod
    def parse(cls, text: str, where: str = "tiles.toml") -> TileIndex:
        """Parses and checks an index's TOML text; raises ``TransportError`` naming
        ``where`` and the problem."""
        try:
            import tomllib
        except ImportError:  # Python 3.10
            try:
                import tomli as tomllib  # type: ignore[no-redef]
            except ImportError:
                raise TransportError(
                    "reading a tile set's index needs Python >= 3.11 (tomllib) or the "
                    "tomli package"
                ) from None

        def invalid(message: str) -> TransportError:
            return TransportError(f"the gateway's tile index {where}: {message}")

        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise invalid(f"not a tile index: {e}") from None
        fmt = doc.get("format")
        if fmt != INDEX_FORMAT or isinstance(fmt, bool):
            raise invalid(
                f"tile index format {fmt!r} (this client reads format {INDEX_FORMAT}): "
                "update the kfmap Python client or re-cut the map"
            )

        def number(key: str) -> float:
            v = doc.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise invalid(f"{key} {v!r} is not a number")
            return float(v)

        size, halo = number("tile-size"), number("halo")
        if not (math.isfinite(size) and 1.0 <= size <= 100_000.0):
            raise invalid(f"tile-size {size} is out of range: 1 to 100000 m")
        if not (math.isfinite(halo) and 0.0 <= halo <= 4.0 * size):
            raise invalid(f"halo {halo} is out of range: 0 m to 4 times the tile size")
        raw = doc.get("tile", [])
        if not isinstance(raw, list) or not raw:
            raise invalid("the index lists no tile")
        tiles, seen = [], set()
        for t in raw:
            if not isinstance(t, dict):
                raise invalid(f"tile entry {t!r} is not a table")
            tid, col, row = t.get("id"), t.get("col"), t.get("row")
            if any(isinstance(v, bool) or not isinstance(v, int) for v in (col, row)):
                raise invalid(f"tile {tid!r}: col {col!r} and row {row!r} must be integers")
            if tid != tile_id(col, row):
                raise invalid(f"tile {tid!r} has col {col} row {row}: its id must be "
                              f"{tile_id(col, row)!r}")
            if (col, row) in seen:
                raise invalid(f"tile {tid} is listed twice")
            seen.add((col, row))
            tiles.append(TileEntry(tid, col, row))
        keyframes = doc.get("keyframes", 0)
        return cls(size, halo, int(keyframes) if isinstance(keyframes, int) else 0,
                   tuple(tiles))

    def distance_to_core(self, i: int, x: float, y: float) -> float:
        """Chebyshev distance from ``(x, y)`` to tile ``i``'s core square (0 inside)."""
        t, s = self.tiles[i], self.tile_size
        x0, y0 = t.col * s, t.row * s
        return max(x0 - x, x - (x0 + s), y0 - y, y - (y0 + s), 0.0)


class TileRouter:
    """Picks the tile a request goes to from its pose guess, staying on the current tile
    near its border (hysteresis, default half the halo), as the Rust ``TileRouter``:

    - the current tile while it is up and the guess within the hysteresis of its core;
    - else the tile whose core holds the guess (the owner), if up;
    - else (the owner down) the nearest live tile within the hysteresis stands in, whose
      halo holds what the request needs; never a farther one (its answer would be
      wrong, not merely late): ``(ROUTE_DOWN, owner)``;
    - a guess outside every core: the live tile whose core is nearest, or
      ``(ROUTE_NONE_UP, None)``;
    - a non-finite guess: the current tile.
    """

    def __init__(self, index: TileIndex, hysteresis: float | None = None) -> None:
        h = index.halo / 2.0 if hysteresis is None else float(hysteresis)
        self.index = index
        self.hysteresis = min(max(h, 0.0), index.halo)
        #: Index of the tile the last request went to (None before the first).
        self.current: int | None = None

    def route(self, x: float, y: float, up: Callable[[int], bool]) -> tuple[str, int | None]:
        """``(ROUTE_TILE, i)``, ``(ROUTE_DOWN, owner)`` or ``(ROUTE_NONE_UP, None)`` for
        a guess at ``(x, y)``; ``up(i)`` says whether tile ``i`` answers."""
        if not (math.isfinite(x) and math.isfinite(y)):
            c = self.current
            if c is None:
                return ROUTE_NONE_UP, None
            return (ROUTE_TILE, c) if up(c) else (ROUTE_DOWN, c)
        index = self.index

        def distance(i: int) -> float:
            return index.distance_to_core(i, x, y)

        c = self.current
        if c is not None and up(c) and distance(c) <= self.hysteresis:
            return ROUTE_TILE, c
        live = [i for i in range(len(index.tiles)) if up(i)]
        nearest = min(live, key=distance) if live else None  # the first of equals
        owner = next((i for i in range(len(index.tiles)) if distance(i) == 0.0), None)
        if owner is not None and up(owner):
            chosen = owner
        elif owner is not None and (nearest is None or distance(nearest) > self.hysteresis):
            return ROUTE_DOWN, owner
        elif nearest is not None:
            chosen = nearest
        else:
            return ROUTE_NONE_UP, None
        self.current = chosen
        return ROUTE_TILE, chosen


# -- relocalization over a tile set ---------------------------------------------------


def _split_answer(frame: bytes) -> tuple[wire.ResponseHeader, bytes]:
    """An answer frame's header and its pairings' bytes."""
    head = C.sizeof(wire.ResponseHeader)
    item = wire.PAIRING_DTYPE.itemsize
    if len(frame) < head or (len(frame) - head) % item:
        raise TransportError(f"the gateway sent a broken answer frame of {len(frame)} bytes")
    return wire.ResponseHeader.from_buffer_copy(frame[:head]), bytes(frame[head:])


def _total_order(v: float) -> int:
    """An integer ordering floats as Rust's ``f64::total_cmp``."""
    bits = struct.unpack("<q", struct.pack("<d", v))[0]
    return bits ^ 0x7FFF_FFFF_FFFF_FFFF if bits < 0 else bits


def _fmax(a: float, b: float) -> float:
    """Rust's ``f64::max``: NaN loses."""
    if math.isnan(a):
        return b
    if math.isnan(b):
        return a
    return max(a, b)


def _distinct(a: Sequence[float], b: Sequence[float]) -> bool:
    """Places farther than ``DISTINCT_M`` or turned more than ``DISTINCT_DEG`` apart
    (an invalid pose is distinct from everything)."""
    if not (wire_pose_is_valid(a) and wire_pose_is_valid(b)):
        return True
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if float(np.linalg.norm(pa[:3] - pb[:3])) > DISTINCT_M:
        return True
    qa, qb = pa[3:] / np.linalg.norm(pa[3:]), pb[3:] / np.linalg.norm(pb[3:])
    w = abs(float(np.dot(qa, qb)))
    angle = 0.0 if w > 1.0 else 2.0 * math.acos(w)
    return math.degrees(angle) > DISTINCT_DEG


def merge_relocalizations(answers: Sequence[tuple[str, bytes]]) -> bytes:
    """Merges the relocalization answer frames of every tile (``(tile, frame)``) into
    one, as ``client/src/tiled.rs`` does: the best place score wins (its status kept
    unless found or ambiguous); the runner-up is the larger of its own runner-up and
    the scores (> 0) of other tiles' places distinct from it, and a runner-up within
    ``AMBIGUITY_MARGIN`` makes a fitting winner ``AMBIGUOUS``, else ``FOUND``;
    candidates add up, ``server_us`` is the slowest tile's. With no ``Ok`` answer the
    first refusal is the answer."""
    if not answers:
        raise TransportError("no tile answered the relocalization")
    decoded = []
    for tile, frame in answers:
        try:
            decoded.append(_split_answer(frame))
        except TransportError as e:
            raise TransportError(f"tile {tile}'s relocalization answer: {e}") from None
    ok = [a for a in decoded if a[0].status == wire.StatusCode.OK]
    if not ok:
        header, pairings = next(a for a in decoded if a[0].status != wire.StatusCode.OK)
        return bytes(C.string_at(C.byref(header), C.sizeof(header))) + pairings
    # The last of equal best scores, as Rust's max_by.
    best = max(range(len(ok)), key=lambda i: (_total_order(ok[i][0].place_scores[0]), i))
    winner, pairings = ok[best]
    header = wire.ResponseHeader.from_buffer_copy(winner)
    others = 0.0
    for i, (h, _) in enumerate(ok):
        if i != best and h.place_scores[0] > 0.0 and _distinct(winner.pose, h.pose):
            others = _fmax(others, h.place_scores[0])
    header.place_scores[1] = _fmax(header.place_scores[1], others)
    header.candidates = sum(h.candidates for h, _ in ok) & 0xFFFF_FFFF
    server_us = 0.0
    for h, _ in ok:
        server_us = _fmax(server_us, h.server_us)
    header.server_us = server_us
    if winner.relocalization in (wire.RelocalizeStatus.FOUND, wire.RelocalizeStatus.AMBIGUOUS):
        close = header.place_scores[1] + AMBIGUITY_MARGIN >= header.place_scores[0]
        header.relocalization = (
            wire.RelocalizeStatus.AMBIGUOUS if close else wire.RelocalizeStatus.FOUND
        )
    return bytes(C.string_at(C.byref(header), C.sizeof(header))) + pairings


def _fetch_index(session, map_name: str) -> TileIndex:
    """The tile index a gateway of ``map_name`` answers (a map served in tiles has one);
    its queryable may reach this session a moment after its tokens."""
    key = f"{_prefix(map_name)}/index"
    deadline = time.monotonic() + CONNECT_WAIT_S
    while time.monotonic() < deadline:
        for reply in session.get(key, timeout=CONNECT_WAIT_S):
            if reply.ok is None:
                continue
            try:
                text = reply.ok.payload.to_string()
            except Exception as e:
                raise TransportError(f"the tile index on {key} is not text: {e}") from None
            return TileIndex.parse(text, key)
        time.sleep(INDEX_RETRY_S)
    raise TransportError(
        f"{map_name} is served in tiles, but no gateway answers its tile index on {key} "
        f"within {CONNECT_WAIT_S:g} s"
    )


# -- the connection -------------------------------------------------------------------


class RemoteConnection:
    """A connection to the server of one map on other hosts, through their gateways: the
    map served whole, one named tile, or (``tile=None`` and the gateways announce tiles)
    every tile of a tile set, each request routed by its pose guess. Calls are
    serialized by a lock, as on :class:`kfmap.transport.Connection`."""

    def __init__(
        self,
        map_name: str,
        endpoint: str,
        timeout: float,
        *,
        zenoh_config: str | os.PathLike | None = None,
        client_id: str | None = None,
        tile: str | None = None,
    ) -> None:
        zenoh = _zenoh()
        _check_chunk("map name", map_name)
        if tile is not None:
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
        self._client_id = client_id
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
        # The tiles whose token is present (their servers answer), kept by the subscriber.
        self._alive: set[str] = set()
        self._alive_lock = threading.Lock()
        pattern = f"{_prefix(map_name)}/*/alive"

        def on_token(sample) -> None:
            t = _tile_of_alive_key(map_name, str(sample.key_expr))
            if t is None:
                return
            with self._alive_lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._alive.add(t)
                else:
                    self._alive.discard(t)

        try:
            self._watch = self._session.liveliness().declare_subscriber(
                pattern, on_token, history=True
            )
            # The tokens alive now; the subscriber keeps the set current after.
            present = []
            for reply in self._session.liveliness().get(pattern, timeout=CONNECT_WAIT_S):
                if reply.ok is not None:
                    t = _tile_of_alive_key(map_name, str(reply.ok.key_expr))
                    if t is not None:
                        present.append(t)
            with self._alive_lock:
                self._alive.update(present)
            where = ", ".join(endpoints)
            #: The tile set's index (None: one tile, or the map served whole).
            self.tile_index: TileIndex | None = None
            self._router: TileRouter | None = None
            if tile is not None:
                self._tiles = [tile]
                no_server = f"{map_name} (tile {tile} at {where})"
            elif not present:
                raise NoServerError(f"{map_name} (remote, at {where})")
            elif all(t == WHOLE_MAP_TILE for t in present):
                self._tiles = [WHOLE_MAP_TILE]
                no_server = f"{map_name} (remote, at {where})"
            else:
                self.tile_index = _fetch_index(self._session, map_name)
                self._router = TileRouter(self.tile_index)
                self._tiles = [t.id for t in self.tile_index.tiles]
                no_server = f"{map_name} (remote, at {where})"
            if not any(self._tile_alive(i) for i in range(len(self._tiles))):
                raise NoServerError(no_server)
        except BaseException:
            self.close()
            raise

    def _tile_alive(self, i: int) -> bool:
        with self._alive_lock:
            return self._tiles[i] in self._alive

    def _describe(self, i: int) -> str:
        if self._router is None and self._tiles[i] == WHOLE_MAP_TILE:
            return self.map_name
        return f"{self.map_name} (remote, tile {self._tiles[i]})"

    @property
    def alive_tiles(self) -> set[str]:
        """The tiles (``"whole"`` for a map served whole) whose gateway announces a live
        server now."""
        with self._alive_lock:
            return set(self._alive) & set(self._tiles)

    @property
    def current_tile(self) -> str | None:
        """The tile the last routed request went to (None before the first); the one
        tile when not routing."""
        if self._router is None:
            return self._tiles[0]
        c = self._router.current
        return None if c is None else self._tiles[c]

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
        """Sends ``header`` with ``payload`` (float32, flat) and waits for the answer: from
        the tile its pose guess routes to, or, relocalizing over a tile set, from every
        tile. Error statuses raise ``ServerError``."""
        with self._lock:
            if self._session is None:
                raise TransportError("the client is closed")
            every_tile = self._router is not None and header.kind == wire.RequestKind.RELOCALIZE
            i = None if every_tile else self._route(header)
            header.version = wire.PROTOCOL_VERSION
            header.client_node[0], header.client_node[1] = self.client_node
            header.request_id = self._next_request_id
            self._next_request_id += 1
            frame = bytes(C.string_at(C.byref(header), C.sizeof(header)))
            if payload is not None and payload.size:
                frame += np.ascontiguousarray(payload, dtype="<f4").tobytes()
            if i is None:
                return self._call_every_tile(frame)
            return self._call_tile(i, frame)

    def _route(self, header: wire.RequestHeader) -> int:
        """The tile a request goes to (NoServerError when its tile is down)."""
        if self._router is None:
            if not self._tile_alive(0):
                raise NoServerError(self._describe(0))
            return 0
        with self._alive_lock:
            up = [t in self._alive for t in self._tiles]
        outcome, i = self._router.route(header.pose[0], header.pose[1], up.__getitem__)
        if outcome == ROUTE_TILE:
            return i
        if outcome == ROUTE_DOWN:
            raise NoServerError(self._describe(i))
        raise NoServerError(f"{self.map_name} (remote: no tile's server answers)")

    def _call_tile(self, i: int, frame: bytes) -> Reply:
        """Sends a request frame to tile ``i`` and waits for its answer."""
        zenoh = _zenoh()
        if not self._tile_alive(i):
            raise NoServerError(self._describe(i))
        answers: list = []
        done = threading.Event()

        def on_reply(reply) -> None:
            answers.append(reply)
            done.set()

        self._session.get(
            f"{_prefix(self.map_name)}/{self._tiles[i]}/rpc/{self._client_id}",
            zenoh.handlers.Callback(on_reply, done.set),
            payload=frame,
            target=zenoh.QueryTarget.BEST_MATCHING,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout,
        )
        deadline = time.monotonic() + self.timeout
        while not done.wait(WATCH_SLICE_S):
            if not self._tile_alive(i):
                raise DisconnectedError(self._describe(i))
            if time.monotonic() >= deadline:
                raise RequestTimeout(self._describe(i), self.timeout)
        if not answers:
            # The query ended with no answer: the gateway's session closed.
            raise DisconnectedError(self._describe(i))
        reply = answers[0]
        if reply.ok is None:
            raise _failure(reply.err.payload.to_string(), self._describe(i), self.timeout)
        return _decode_answer(reply.ok.payload.to_bytes())

    def _call_every_tile(self, frame: bytes) -> Reply:
        """Sends a relocalization to every tile at once (``QueryTarget.ALL``) and merges
        the answers of as many tiles as were alive when it was sent."""
        zenoh = _zenoh()
        expected = sum(self._tile_alive(i) for i in range(len(self._tiles)))
        if expected == 0:
            raise NoServerError(f"{self.map_name} (remote: no tile's server answers)")
        replies: queue.Queue = queue.Queue()
        self._session.get(
            f"{_prefix(self.map_name)}/*/rpc/{self._client_id}",
            zenoh.handlers.Callback(replies.put, lambda: replies.put(None)),
            payload=frame,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout,
        )
        deadline = time.monotonic() + self.timeout
        answers: list[tuple[str, bytes]] = []
        failures: list[Exception] = []
        while len(answers) + len(failures) < expected and time.monotonic() < deadline:
            try:
                reply = replies.get(timeout=WATCH_SLICE_S)
            except queue.Empty:
                continue
            if reply is None:  # the query ended
                break
            if reply.ok is not None:
                tile = _tile_of_rpc_key(self.map_name, str(reply.ok.key_expr)) or "?"
                answers.append((tile, reply.ok.payload.to_bytes()))
            else:
                failures.append(_failure(
                    reply.err.payload.to_string(), f"{self.map_name} (remote)", self.timeout
                ))
        if len(answers) < expected:
            # A ranking without every tile is not the one search it stands for.
            if failures:
                raise failures[-1]
            raise RequestTimeout(
                f"{self.map_name} (remote, {len(answers)} of {expected} tiles answered)",
                self.timeout,
            )
        return _decode_answer(merge_relocalizations(answers))


def _decode_answer(frame: bytes) -> Reply:
    header, rest = _split_answer(frame)
    if header.status != wire.StatusCode.OK:
        raise ServerError(header.status, header.message_text, header.detail)
    pairings = np.frombuffer(rest, dtype=wire.PAIRING_DTYPE).copy()
    return Reply(header, pairings)
