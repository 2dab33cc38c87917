"""The remote side of a connection: requests as Zenoh queries to the ``kfmap gateway`` of
each host, which answers them through its local server (``client/src/remote.rs``).

A frame is the request's header bytes followed by its float32 payload; the answer is
the response header's bytes followed by its pairings (docs/PROTOCOL.md, "Remote
frames"). A map served in tiles (``kfmap bake --tile-size``, docs/DESIGN.md#notes-tiles)
is learned from a gateway's tile index: each request goes to the tile its pose guess
routes to (:class:`TileRouter`), and a relocalization runs the steps of one search over
the whole map in three phases: every tile's places at once, the best of them all scored
by their tiles, the best score finished by its tile (:func:`choose_places`,
:func:`best_scored`, :func:`finish`). Needs
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
#: Place search keeping (``SearchParams`` defaults): places closer than this (metres) ...
SEPARATION_M = 2.0
#: ... and turned less than this (degrees) are one place ...
SEPARATION_DEG = 20.0
#: ... and a place below this share of the best hit ratio is not kept.
KEEP_RATIO = 0.7
#: Rounding of a place's f32 wire pose (metres, degrees), as ``client/src/tiled.rs``.
WIRE_SLACK_M = 1e-3
WIRE_SLACK_DEG = 1e-3

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
class Ranking:
    """How the tiles' servers rank relocalization places (their ``[relocalize]``
    settings, ``kfmap_map::tiles::PlaceRanking``), as a gateway publishes them with the
    tile index; the defaults are the servers' defaults."""

    keep_ratio: float = KEEP_RATIO
    separation_m: float = SEPARATION_M
    separation_deg: float = SEPARATION_DEG
    ambiguity_margin: float = AMBIGUITY_MARGIN
    distinct_m: float = DISTINCT_M
    distinct_deg: float = DISTINCT_DEG

    #: The ``[ranking]`` keys, as the Rust side names them.
    KEYS = ("keep-ratio", "separation-m", "separation-deg", "ambiguity-margin",
            "distinct-m", "distinct-deg")

    @classmethod
    def parse(cls, table: object, invalid) -> Ranking:
        """A ``[ranking]`` table, checked as ``PlaceRanking::validate`` (the server's own
        bounds: ratios within [0, 1], distances and angles finite and > 0)."""
        if not isinstance(table, dict) or set(table) != set(cls.KEYS):
            raise invalid(f"ranking {table!r} must have exactly the keys {', '.join(cls.KEYS)}")
        values = []
        for key in cls.KEYS:
            v = table[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise invalid(f"ranking {key} {v!r} is not a number")
            v = float(v)
            unit = key in ("keep-ratio", "ambiguity-margin")
            if unit and not 0.0 <= v <= 1.0:
                raise invalid(f"ranking {key} {v} is not within [0, 1]")
            if not unit and not (math.isfinite(v) and v > 0.0):
                raise invalid(f"ranking {key} {v} is not finite and > 0")
            values.append(v)
        return cls(*values)


@dataclass(frozen=True)
class TileIndex:
    """A tile set's index (``tiles.toml``, format 1) as far as routing needs it: tile
    ``(col, row)``'s core square is ``[col s, (col+1) s) x [row s, (row+1) s)`` for
    ``s = tile_size``; its file also holds every keyframe within ``halo`` of it."""

    tile_size: float
    halo: float
    keyframes: int
    tiles: tuple[TileEntry, ...]
    #: True when the index gives the tiles' search regions (``search-min``): the tiles
    #: then split a relocalization's search among them, each translation tried once.
    shares_search: bool = False
    #: The servers' ranking settings when the gateway published them (``[ranking]``).
    ranking: Ranking | None = None

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
        shares = any(isinstance(t, dict) and "search-min" in t for t in raw)
        ranking = Ranking.parse(doc["ranking"], invalid) if "ranking" in doc else None
        return cls(size, halo, int(keyframes) if isinstance(keyframes, int) else 0,
                   tuple(tiles), shares, ranking)

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


def _distinct(a: Sequence[float], b: Sequence[float], ranking: Ranking) -> bool:
    """Places farther than ``distinct_m`` or turned more than ``distinct_deg`` apart
    (an invalid pose is distinct from everything)."""
    if not (wire_pose_is_valid(a) and wire_pose_is_valid(b)):
        return True
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if float(np.linalg.norm(pa[:3] - pb[:3])) > ranking.distinct_m:
        return True
    qa, qb = pa[3:] / np.linalg.norm(pa[3:]), pb[3:] / np.linalg.norm(pb[3:])
    w = abs(float(np.dot(qa, qb)))
    angle = 0.0 if w > 1.0 else 2.0 * math.acos(w)
    return math.degrees(angle) > ranking.distinct_deg


def _same_place(a: Sequence[float], b: Sequence[float], ranking: Ranking) -> bool:
    """Placements within ``separation_m`` and ``separation_deg`` of each other."""
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    # Lattice placements often lie exactly the separation apart (distinct to the search):
    # the wire's f32 must not make them one (``WIRE_SLACK_M``, ``WIRE_SLACK_DEG``).
    if float(np.linalg.norm(pa[:3] - pb[:3])) >= ranking.separation_m - WIRE_SLACK_M:
        return False
    qa, qb = pa[3:] / np.linalg.norm(pa[3:]), pb[3:] / np.linalg.norm(pb[3:])
    w = abs(float(np.dot(qa, qb)))
    angle = 0.0 if w > 1.0 else 2.0 * math.acos(w)
    return math.degrees(angle) < ranking.separation_deg - WIRE_SLACK_DEG


def choose_places(answers: Sequence[tuple[str, bytes]], cores: "TileIndex | None" = None,
                  ranking: Ranking = Ranking(),
                  ) -> tuple[bytes | None, list[tuple[str, int]], list[tuple[str, int]], float]:
    """The first phase's decision, as ``client/src/tiled.rs`` ``choose_places``: every
    tile's proposed places (``(tile, FLAG_PLACES_ONLY answer frame)``) ranked by hit
    ratio (ties by tile id, then rank), the best ``max(detail)`` kept as one search keeps
    them: a place within the separation of a better one is the same place (neighbours'
    regions overlap), one below ``ranking.keep_ratio`` of the best is dropped, and a tile's relief
    places (``reasons`` has ``PLACES_FROM_RELIEF``) count only when no tile proposed from
    structure, as one search of the whole map falls back; with ``cores`` (the tile
    index) a neighbour's copy of a place in an answering tile's core is left out, the
    owner's kept. Returns ``(frame,
    [], [], searched_us)`` when the answer stands (a tile's refusal, or no place
    anywhere: not found), else ``(None, [(tile, rank bits)], order, searched_us)`` with
    ``order`` every chosen ``(tile, rank)`` as one search would rank them."""
    if not answers:
        raise TransportError("no tile answered the relocalization")
    # (hit ratio's total order, tile, rank, wire pose, hit ratio)
    structure: list[tuple[int, str, int, list[float], float]] = []
    relief: list[tuple[int, str, int, list[float], float]] = []
    keep, searched_us, first = 0, 0.0, None
    for tile, frame in answers:
        try:
            header, rest = _split_answer(frame)
        except TransportError as e:
            raise TransportError(f"tile {tile}'s proposed places: {e}") from None
        if header.status != wire.StatusCode.OK:
            return frame, [], [], 0.0
        slots = np.frombuffer(rest, dtype=wire.PLACE_DTYPE)
        if len(slots) != header.candidates:
            raise TransportError(
                f"tile {tile} proposed {header.candidates} places but sent {len(slots)}"
            )
        first = header if first is None else first
        keep = max(keep, min(header.detail, 64))
        searched_us = _fmax(searched_us, header.server_us)
        into = relief if header.reasons & wire.PLACES_FROM_RELIEF else structure
        for rank, slot in enumerate(slots):
            pose = [float(v) for v in slot["translation"]] + [float(v) for v in slot["rotation"]]
            hits = float(slot["score"])
            into.append((_total_order(hits), tile, rank, pose, hits))
    proposed = sorted(structure or relief, key=lambda p: (-p[0], p[1], p[2]))
    if cores is not None:
        # A neighbour's copy of a place in an answering tile's core is left out: the
        # owner holds the keyframes nearest it.
        answered = {tile for tile, _ in answers}
        size = cores.tile_size

        def owned(tile: str, pose: list[float]) -> bool:
            owner = tile_id(math.floor(pose[0] / size), math.floor(pose[1] / size))
            return owner == tile or owner not in answered

        proposed = [p for p in proposed if owned(p[1], p[3])]
    places: list[tuple[int, str, int, list[float], float]] = []
    if proposed:
        floor = ranking.keep_ratio * proposed[0][4]
        for place in proposed:
            if len(places) == keep or place[4] < floor:
                break
            if not any(_same_place(kept[3], place[3], ranking) for kept in places):
                places.append(place)
    if not places:
        header = wire.ResponseHeader.from_buffer_copy(first)
        header.relocalization = wire.RelocalizeStatus.NOT_FOUND
        header.candidates = 0
        header.place_scores[0] = header.place_scores[1] = 0.0
        header.detail = 0
        header.server_us = searched_us
        return _header_bytes(header), [], [], searched_us
    chosen: dict[str, int] = {}
    for _, tile, rank, _, _ in places:
        chosen[tile] = chosen.get(tile, 0) | (1 << rank)
    return None, list(chosen.items()), [(t, r) for _, t, r, _, _ in places], searched_us


@dataclass
class Ranked:
    """Every scored place of the second phase (:func:`best_scored`)."""

    best: tuple[str, int] | None
    places: list[tuple[str, int, list[float], float]]  # tile, rank, wire pose, score
    candidates: int
    registrations: int
    scored_us: float


def best_scored(order: Sequence[tuple[str, int]],
                answers: Sequence[tuple[str, bytes]]) -> Ranked | bytes:
    """Reads the ``FLAG_SCORE_CHOSEN`` answers (``(tile, frame)``) of the places chosen
    in ``order`` and finds the best score as one server would (places in the search's
    order, the first of equal scores), as ``client/src/tiled.rs``. A refusal is returned
    as the answer frame."""
    position = {place: i for i, place in enumerate(order)}
    places, candidates, registrations, scored_us = [], 0, 0, 0.0
    for tile, frame in answers:
        try:
            header, rest = _split_answer(frame)
        except TransportError as e:
            raise TransportError(f"tile {tile}'s scored places: {e}") from None
        if header.status != wire.StatusCode.OK:
            return frame
        candidates += header.candidates
        registrations += header.registrations
        scored_us = _fmax(scored_us, header.server_us)
        for slot in np.frombuffer(rest, dtype=wire.PLACE_DTYPE):
            pose = wire.place_pose(slot)
            if not wire_pose_is_valid(pose):
                raise TransportError(f"tile {tile} scored an invalid pose")
            places.append((tile, int(slot["rank"]), pose, float(slot["score"])))
    if any((t, r) not in position for t, r, _, _ in places):
        raise TransportError("a tile scored a place that was not chosen")
    places.sort(key=lambda p: position[(p[0], p[1])])
    best = None
    for place in places:
        if best is None or place[3] > best[3]:
            best = place
    return Ranked(None if best is None else (best[0], best[1]), places,
                  candidates & 0xFFFF_FFFF, registrations & 0xFFFF_FFFF, scored_us)


def nothing_settled(ranked: Ranked, searched_us: float) -> bytes:
    """The answer when no chosen place settled: not found, as on one server."""
    header = wire.ResponseHeader(relocalization=wire.RelocalizeStatus.NOT_FOUND,
                                 candidates=ranked.candidates,
                                 registrations=ranked.registrations,
                                 server_us=searched_us + ranked.scored_us)
    return _header_bytes(header)


def finish(frame: bytes, ranked: Ranked, searched_us: float,
           ranking: Ranking = Ranking()) -> bytes:
    """The final answer from the best place's ``FLAG_FINISH_CHOSEN`` answer frame, as
    ``client/src/tiled.rs`` ``finish``: the runner-up is the best score among the other
    scored places distinct from where the best settled (farther than
    ``ranking.distinct_m`` or turned more than ``ranking.distinct_deg``); within
    ``ranking.ambiguity_margin`` a fitting answer is ``AMBIGUOUS``, else ``FOUND``; a
    place that does not fit is ``NOT_FOUND``. Every tile's scored places travel in the
    pairings' slots (settled pose, score, rank in the search's order), as one server
    sends its scored places."""
    header, _own_places = _split_answer(frame)
    if header.status != wire.StatusCode.OK:
        return frame
    header.candidates = ranked.candidates
    header.registrations = (header.registrations + ranked.registrations) & 0xFFFF_FFFF
    header.server_us += searched_us + ranked.scored_us
    fits = header.relocalization != wire.RelocalizeStatus.NOT_FOUND
    if fits and ranked.best is not None and wire_pose_is_valid(header.pose):
        runner_up = 0.0
        for tile, rank, pose, score in ranked.places:
            if (tile, rank) != ranked.best and _distinct(header.pose, pose, ranking):
                runner_up = _fmax(runner_up, score)
        header.place_scores[1] = runner_up
        close = runner_up + ranking.ambiguity_margin >= header.place_scores[0]
        header.relocalization = (
            wire.RelocalizeStatus.AMBIGUOUS if close else wire.RelocalizeStatus.FOUND
        )
    slots = np.zeros(len(ranked.places), dtype=wire.PLACE_DTYPE)
    for rank, (_, _, pose, score) in enumerate(ranked.places):
        slots[rank] = (pose[:3], pose[3:], score, rank)
    return _header_bytes(header) + slots.tobytes()


def _header_bytes(header: wire.ResponseHeader) -> bytes:
    return bytes(C.string_at(C.byref(header), C.sizeof(header)))


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
            # The tokens alive now; the subscriber keeps the set current after. Asked
            # again until one shows or CONNECT_WAIT_S is spent: the session may not have
            # reached a gateway yet when the first ask goes out (a loaded host).
            present: list[str] = []
            deadline = time.monotonic() + CONNECT_WAIT_S
            while True:
                left = max(0.05, deadline - time.monotonic())
                for reply in self._session.liveliness().get(pattern, timeout=left):
                    if reply.ok is not None:
                        t = _tile_of_alive_key(map_name, str(reply.ok.key_expr))
                        if t is not None:
                            present.append(t)
                with self._alive_lock:
                    present.extend(self._alive)
                if present or time.monotonic() >= deadline:
                    break
                time.sleep(0.05)
            present = sorted(set(present))
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
            body = b""
            if payload is not None and payload.size:
                body = np.ascontiguousarray(payload, dtype="<f4").tobytes()
            if i is None:
                return self._call_every_tile(header, body)
            return self._call_tile(i, _frame(header, body))

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

    def _call_every_tile(self, header: wire.RequestHeader, body: bytes) -> Reply:
        """Relocalizes over every tile as one search over the merged map would, in three
        phases: every tile's places at once, the best of them all scored by the tiles
        holding them, the best score finished by its tile (:func:`choose_places`,
        :func:`best_scored`, :func:`finish`)."""
        started = time.monotonic()

        def left() -> float:
            return max(0.0, self.timeout - (time.monotonic() - started))

        def phase(flag: int, ranks: int) -> bytes:
            h = wire.RequestHeader.from_buffer_copy(header)
            h.flags |= flag
            h.keyframe_or_scan_id = ranks
            return _frame(h, body)

        def tile_number(tile: str) -> int:
            if tile not in self._tiles:
                raise TransportError(
                    f"an answer came from tile {tile!r}, which is not in "
                    f"{self.map_name}'s tile index"
                )
            return self._tiles.index(tile)

        places = self._ask_every_tile(phase(wire.FLAG_PLACES_ONLY, 0))
        # Tiles that split the search propose each place once; older cuts' tiles
        # overlap, and a neighbour's copy of a place in an answering core is dropped.
        index = self.tile_index
        overlapping = None if index is None or index.shares_search else index
        # The servers' ranking as their gateway published it (defaults from an older one).
        ranking = (index.ranking if index is not None else None) or Ranking()
        frame, chosen, order, searched_us = choose_places(places, overlapping, ranking)
        if frame is not None:
            return _decode_answer(frame)
        requests = [(tile_number(t), phase(wire.FLAG_SCORE_CHOSEN, bits)) for t, bits in chosen]
        ranked = best_scored(order, self._ask_tiles(requests, left()))
        if isinstance(ranked, bytes):
            return _decode_answer(ranked)
        if ranked.best is None:
            return _decode_answer(nothing_settled(ranked, searched_us))
        tile, rank = ranked.best
        finished = self._ask_tiles([(tile_number(tile), phase(wire.FLAG_FINISH_CHOSEN, 1 << rank))],
                                   left())
        return _decode_answer(finish(finished[0][1], ranked, searched_us, ranking))

    def _ask_tiles(self, requests: list[tuple[int, bytes]], timeout: float) -> list[tuple[str, bytes]]:
        """Sends request frames to tiles (each its own) at once and waits for every
        answer frame (``(tile, frame)``)."""
        zenoh = _zenoh()
        pending = []
        for i, frame in requests:
            if not self._tile_alive(i):
                raise DisconnectedError(self._describe(i))
            replies: queue.Queue = queue.Queue()
            self._session.get(
                f"{_prefix(self.map_name)}/{self._tiles[i]}/rpc/{self._client_id}",
                zenoh.handlers.Callback(replies.put, lambda q=replies: q.put(None)),
                payload=frame,
                target=zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout,
            )
            pending.append((i, replies))
        deadline = time.monotonic() + timeout
        answers: list[tuple[str, bytes]] = []
        while pending:
            i, replies = pending[0]
            try:
                reply = replies.get(timeout=WATCH_SLICE_S)
            except queue.Empty:
                reply = False
            if reply is None:
                # The query ended with no answer: the gateway's session closed.
                raise DisconnectedError(self._describe(i))
            if reply is not False:
                if reply.ok is None:
                    raise _failure(reply.err.payload.to_string(), self._describe(i), timeout)
                answers.append((self._tiles[i], reply.ok.payload.to_bytes()))
                pending.pop(0)
                continue
            for j, _ in pending:
                if not self._tile_alive(j):
                    raise DisconnectedError(self._describe(j))
            if time.monotonic() >= deadline:
                raise RequestTimeout(self._describe(i), timeout)
        return answers

    def _ask_every_tile(self, frame: bytes) -> list[tuple[str, bytes]]:
        """Sends one request frame to every tile at once (``QueryTarget.ALL``) and waits
        for the answers of as many tiles as were alive when it was sent."""
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
        return answers


def _frame(header: wire.RequestHeader, body: bytes) -> bytes:
    """A request frame: the header's bytes, then the payload's."""
    return bytes(C.string_at(C.byref(header), C.sizeof(header))) + body


def _decode_answer(frame: bytes) -> Reply:
    header, rest = _split_answer(frame)
    if header.status != wire.StatusCode.OK:
        raise ServerError(header.status, header.message_text, header.detail)
    pairings = np.frombuffer(rest, dtype=wire.PAIRING_DTYPE).copy()
    return Reply(header, pairings)
