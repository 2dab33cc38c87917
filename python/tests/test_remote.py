"""``Client.remote`` through a ``kfmap gateway`` (Zenoh over TCP) against the session's
test server, checked against the local client (iceoryx2) on the same server: every
remote answer must equal its local twin. Then a tile set on two emulated hosts (each a
``kfmap serve --tiles --only`` + ``kfmap gateway --tiles --only`` pair), driven through
one remote client routing by pose guess, against the merged map served whole. The
router and the relocalization merge are also checked on hand-made inputs.

Network tests run only inside a private network namespace (``unshare -rn``: only ``lo``
exists), which ``run_tests.sh`` creates for this file and marks with
``KFMAP_TEST_NETNS=1``; elsewhere they skip (and fail under ``CI=true``).
"""

from __future__ import annotations

import atexit
import ctypes
import dataclasses
import json
import math
import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import kfmap
from _data import ground_truth, scan_points
from conftest import READY_TIMEOUT_S, _stop, remove_prefix_files
from kfmap import remote as kr
from kfmap import wire

ENDPOINT = "tcp/127.0.0.1:17449"


def _in_namespace() -> bool:
    return os.environ.get("KFMAP_TEST_NETNS") == "1"


def _require_namespace() -> None:
    if not _in_namespace():
        reason = "remote tests run only in the network namespace run_tests.sh creates"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{reason}, and CI=true: run them through python/run_tests.sh")
        pytest.skip(reason)
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    assert [line.split(":")[1].strip() for line in links.splitlines()] == ["lo"], links


@pytest.fixture(scope="module")
def gateway(kfmap_bin, server):
    _require_namespace()
    process = subprocess.Popen(
        [kfmap_bin, "gateway", "--map-name", server.map_name, "--iceoryx-prefix",
         server.prefix, "--listen", ENDPOINT],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )
    line = []
    reader = threading.Thread(target=lambda: line.append(process.stdout.readline()))
    reader.start()
    reader.join(timeout=60)
    assert line and line[0].startswith("ready: gateway"), line
    yield process
    process.kill()
    process.wait(timeout=10)


def test_remote_answers_equal_the_local_clients(gateway, server, client):
    points, _ = scan_points(server.dataset, 12)
    truth = ground_truth(server.dataset)[12, 1:]
    guess = truth.copy()
    guess[0] += 0.1
    with kfmap.Client.remote(ENDPOINT, server.map_name, timeout=20.0) as remote:
        assert remote.status().keyframes == client.status().keyframes
        a = remote.nearest(points[::5], guess, k=2)
        b = client.nearest(points[::5], guess, k=2)
        for field in ("query", "keyframe", "local_index", "point", "dist_sq"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        ra = remote.localize(points, guess)
        rb = client.localize(points, guess)
        np.testing.assert_array_equal(ra.pose, rb.pose)
        assert ra.status == rb.status
        assert np.linalg.norm(ra.pose[:3, 3] - truth[:3]) < 0.05


def test_remote_refusals_and_bad_endpoints_name_the_problem(gateway, server):
    with kfmap.Client.remote(ENDPOINT, server.map_name, timeout=20.0) as remote:
        with pytest.raises(kfmap.ServerError) as error:
            remote.nearest(np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0]]), np.eye(4))
        assert error.value.status == kfmap.StatusCode.NON_FINITE_POINT
    with pytest.raises(kfmap.NoServerError):
        kfmap.Client.remote(ENDPOINT, "no-such-map", timeout=5.0)
    with pytest.raises(kfmap.InvalidArgument):
        kfmap.Client.remote(ENDPOINT, "bad/name")
    with pytest.raises(kfmap.TransportError):
        kfmap.Client.remote("tcp/127.0.0.1:1", server.map_name)


# -- tile sets: the router and the relocalization merge on hand-made inputs ----------


def _index(tiles: list[tuple[int, int]], size: float, halo: float) -> kr.TileIndex:
    """A tile index as ``kfmap bake --tile-size`` writes it (files and counts made up)."""
    entries = "".join(
        f'[[tile]]\nid = "x{c}_y{r}"\ncol = {c}\nrow = {r}\nfile = "x{c}_y{r}.kfmap"\n'
        f'pcd = "x{c}_y{r}.pcd"\nkeyframes = 3\ncore-keyframes = 1\npoints = 9\nbytes = 99\n\n'
        for c, r in tiles
    )
    text = f"format = 1\ntile-size = {size}\nhalo = {halo}\nkeyframes = 7\n\n{entries}"
    return kr.TileIndex.parse(text)


def test_the_router_keeps_its_tile_within_half_the_halo_and_never_sends_far():
    tile, down, none_up = kr.ROUTE_TILE, kr.ROUTE_DOWN, kr.ROUTE_NONE_UP
    index = _index([(0, 0), (1, 0)], 10.0, 4.0)  # cores [0,10) and [10,20) on x, [0,10) on y
    assert [t.id for t in index.tiles] == ["x0_y0", "x1_y0"]
    every = lambda i: True  # noqa: E731
    nothing = lambda i: False  # noqa: E731
    router = kr.TileRouter(index)
    assert router.hysteresis == 2.0 and router.current is None
    assert kr.TileRouter(index, 9.0).hysteresis == 4.0  # at most the halo
    assert router.route(9.0, 5.0, every) == (tile, 0)
    assert router.route(11.5, 5.0, every) == (tile, 0)  # 1.5 m past the border: stays
    assert router.route(12.5, 5.0, every) == (tile, 1)  # 2.5 m past it: hands over
    assert router.route(8.5, 5.0, every) == (tile, 1)  # ... and stays back to 1.5 m
    assert router.route(7.5, 5.0, every) == (tile, 0)
    assert router.current == 0
    # Past the top edge (outside every core): the current tile within 2 m, else the
    # nearest live tile (at (15, 11.5) tile 0 is 5 m away, tile 1 1.5 m).
    assert router.route(9.0, 11.5, every) == (tile, 0)
    assert router.route(15.0, 11.5, every) == (tile, 1)
    assert router.route(8.5, 11.5, every) == (tile, 1)
    assert router.route(5.0, 13.0, every) == (tile, 0)  # 3 m from tile 0, 5 m from tile 1
    # The current tile down: the owner takes over.
    assert router.route(1.0, 1.0, lambda i: i == 0) == (tile, 0)
    # The owner down: a neighbour within 2 m of the guess stands in, a farther one never.
    fresh = kr.TileRouter(index)
    assert fresh.route(11.0, 5.0, lambda i: i == 0) == (tile, 0)
    assert fresh.route(15.0, 5.0, lambda i: i == 0) == (down, 1)
    assert fresh.route(15.0, 5.0, nothing) == (down, 1)
    assert fresh.current == 0
    # Outside every core: the nearest live tile, or none.
    fresh = kr.TileRouter(index)
    assert fresh.route(40.0, -3.0, every) == (tile, 1)
    assert kr.TileRouter(index).route(-30.0, 3.0, lambda i: i == 1) == (tile, 1)
    assert kr.TileRouter(index).route(40.0, -3.0, nothing) == (none_up, None)
    # A non-finite guess: the current tile (none yet: nowhere to go).
    assert kr.TileRouter(index).route(math.nan, 0.0, every) == (none_up, None)
    assert fresh.route(math.inf, 5.0, every) == (tile, 1)
    assert fresh.route(math.nan, 5.0, lambda i: i == 0) == (down, 1)
    # Chebyshev distance to a core square, 0 inside.
    assert index.distance_to_core(0, 5.0, 5.0) == 0.0
    assert index.distance_to_core(0, 13.0, -1.0) == 3.0
    assert index.distance_to_core(1, 5.0, 14.0) == 5.0


def test_a_bad_tile_index_is_refused_naming_the_problem():
    good = _index([(-1, 2)], 250.0, 50.0)
    assert (good.tile_size, good.halo, good.keyframes) == (250.0, 50.0, 7)
    assert good.tiles == (kr.TileEntry("x-1_y2", -1, 2),)
    cases = [
        ("format = 2\ntile-size = 10.0\nhalo = 1.0\n", "format 2"),
        ("format = 1\ntile-size = 10.0\nhalo = 1.0\n", "no tile"),
        ("format = 1\ntile-size = 10.0\nhalo = 50.0\n[[tile]]\nid = 'x0_y0'\ncol = 0\nrow = 0\n",
         "halo 50.0"),
        ("format = 1\ntile-size = 10.0\nhalo = 1.0\n[[tile]]\nid = 'x5_y5'\ncol = 0\nrow = 0\n",
         "its id must be 'x0_y0'"),
        ("format = 1\ntile-size = 10.0\nhalo = 1.0\n[[tile]]\nid = 'x0_y0'\ncol = 0\nrow = 0\n"
         "[[tile]]\nid = 'x0_y0'\ncol = 0\nrow = 0\n", "listed twice"),
        ("format = 1\ntile-size = [\n", "not a tile index"),
    ]
    for text, expected in cases:
        with pytest.raises(kfmap.TransportError, match=expected):
            kr.TileIndex.parse(text)
    # A published ranking (``[ranking]``) is read, and refused where the servers' own
    # check (``PlaceRanking::validate``) refuses it, naming the key.
    one_tile = "format = 1\ntile-size = 10.0\nhalo = 1.0\n[[tile]]\nid = 'x0_y0'\ncol = 0\nrow = 0\n"
    ranking = ("[ranking]\nkeep-ratio = 0.6\nseparation-m = 2.0\nseparation-deg = 20.0\n"
               "ambiguity-margin = 0.2\ndistinct-m = 1.0\ndistinct-deg = 5.0\n")
    assert kr.TileIndex.parse(one_tile + ranking).ranking == kr.Ranking(
        keep_ratio=0.6, ambiguity_margin=0.2)
    for old, new, expected in [("distinct-m = 1.0", "distinct-m = 0.0", "distinct-m"),
                               ("keep-ratio = 0.6", "keep-ratio = 1.5", "keep-ratio"),
                               ("separation-deg = 20.0", "separation-deg = nan", "separation-deg"),
                               ("distinct-deg = 5.0\n", "", "exactly the keys")]:
        with pytest.raises(kfmap.TransportError, match=expected):
            kr.TileIndex.parse(one_tile + ranking.replace(old, new))


FOUND, AMBIGUOUS, NOT_FOUND = (
    wire.RelocalizeStatus.FOUND, wire.RelocalizeStatus.AMBIGUOUS, wire.RelocalizeStatus.NOT_FOUND)


def _at(x: float, yaw_deg: float = 0.0) -> list[float]:
    half = math.radians(yaw_deg) / 2.0
    return [x, 0.0, 0.0, 0.0, 0.0, math.sin(half), math.cos(half)]


def _places(places: list[tuple[list[float], float, int]], candidates: int, detail: int = 0, *,
            code: int = wire.StatusCode.OK) -> bytes:
    """An answer frame carrying ``places`` (wire pose, score, rank)."""
    h = wire.ResponseHeader(status=code, candidates=candidates, detail=detail,
                            registrations=2 * candidates, server_us=100.0 * len(places))
    slots = np.zeros(len(places), dtype=wire.PLACE_DTYPE)
    for i, (pose, score, rank) in enumerate(places):
        slots[i]["translation"] = pose[:3]
        slots[i]["rotation"] = pose[3:]
        slots[i]["score"] = score
        slots[i]["rank"] = rank
    return ctypes.string_at(ctypes.byref(h), ctypes.sizeof(h)) + slots.tobytes()


def _proposed(hits: list[float], detail: int) -> bytes:
    """Places of these hit ratios, each at its own spot (x = 100 times its ratio)."""
    return _places([(_at(100.0 * h), h, r) for r, h in enumerate(hits)], len(hits), detail)


def test_places_are_kept_as_one_search_keeps_them_across_tiles():
    # The same placement from two tiles is one place, the better one's; within 2 m and
    # 20 deg of a better one it is the same place; turned 30 deg it is another; 0.6 is
    # below KEEP_RATIO of the best 0.9.
    answers = [("t0", _places([(_at(0.0), 0.9, 0), (_at(50.0), 0.8, 1)], 2, 6)),
               ("t1", _places([(_at(0.0), 0.85, 0), (_at(1.5, 10.0), 0.84, 1)], 2, 6)),
               ("t2", _places([(_at(0.0, 30.0), 0.83, 0), (_at(80.0), 0.6, 1)], 2, 6))]
    assert kr.choose_places(answers)[2] == [("t0", 0), ("t2", 0), ("t0", 1)]
    # With 10 m cores, x0_y0 owns the origin: its copy stands, whatever a neighbour's
    # hit ratio; a place in a core no tile answered for stays with its proposer.
    cores = kr.TileIndex(10.0, 5.0, 0, ())
    answers = [("x-1_y0", _places([(_at(0.0), 0.9, 0)], 1, 6)),
               ("x0_y0", _places([(_at(0.0), 0.85, 0)], 1, 6)),
               ("x0_y-1", _places([(_at(12.0, 90.0), 0.8, 0)], 1, 6))]
    assert kr.choose_places(answers, cores)[2] == [("x0_y0", 0), ("x0_y-1", 0)]
    # Exactly the separation apart (lattice placements 2 m apart in z, through the wire's
    # f32 at a site's coordinates): two places, as the search keeps them.
    below, up = _at(1234.567), _at(1234.567)
    below[2], up[2] = 1.0, 3.0
    answers = [("t0", _places([(below, 0.9, 0), (up, 0.89, 1)], 2, 6))]
    assert kr.choose_places(answers)[2] == [("t0", 0), ("t0", 1)]


def _from_relief(hits: list[float], detail: int) -> bytes:
    """A tile's answer whose places come from its relief search."""
    frame = bytearray(_proposed(hits, detail))
    h = _header(bytes(frame))
    h.reasons = wire.PLACES_FROM_RELIEF
    frame[:ctypes.sizeof(h)] = ctypes.string_at(ctypes.byref(h), ctypes.sizeof(h))
    return bytes(frame)


def test_relief_places_stand_only_when_no_tile_proposed_from_structure():
    # One search of the merged map proposes from structure when any tile can.
    answers = [("t0", _from_relief([0.95, 0.9], 3)), ("t1", _proposed([0.6], 3)),
               ("t2", _from_relief([0.7], 3))]
    assert kr.choose_places(answers)[2] == [("t1", 0)]
    # No tile proposed from structure: every tile's relief places rank together.
    answers = [("t0", _from_relief([0.55, 0.5], 3)), ("t1", _from_relief([0.7], 3))]
    assert kr.choose_places(answers)[2] == [("t1", 0), ("t0", 0), ("t0", 1)]


def _header(frame: bytes) -> wire.ResponseHeader:
    return wire.ResponseHeader.from_buffer_copy(frame[:ctypes.sizeof(wire.ResponseHeader)])


def test_the_best_places_of_every_tile_are_chosen_as_one_search_keeps_its_best():
    hits = [[0.9, 0.5, 0.4], [0.8, 0.7], [0.3], []]
    answers = [(f"t{i}", _proposed(h, 3)) for i, h in enumerate(hits)]
    frame, chosen, order, searched_us = kr.choose_places(answers)
    # Brute force over every (tile, rank): the 3 best hit ratios overall.
    every = sorted(((x, f"t{t}", r) for t, h in enumerate(hits) for r, x in enumerate(h)),
                   key=lambda p: -p[0])[:3]
    assert order == [(t, r) for _, t, r in every]
    assert frame is None and chosen == [("t0", 0b1), ("t1", 0b11)] and searched_us == 300.0
    # No place anywhere: not found at once.
    frame, chosen, _, _ = kr.choose_places([("t0", _proposed([], 5))])
    h = _header(frame)
    assert chosen == [] and h.relocalization == NOT_FOUND and h.candidates == 0
    # A tile's refusal is the answer: a ranking without it is not one search.
    refused = _places([], 0, code=wire.StatusCode.BUSY)
    frame, chosen, _, _ = kr.choose_places([("t0", _proposed([0.9], 5)), ("t1", refused)])
    assert frame == refused and chosen == []
    # A frame whose places disagree with its count is an error, not a guess.
    with pytest.raises(kfmap.TransportError, match="proposed 2 places but sent 1"):
        kr.choose_places([("t0", _proposed([0.9, 0.8], 5)[:-56])])


def _finished(settled: list[float], score: float, fits: bool) -> bytes:
    """The finishing tile's answer: found when it fits, no runner-up."""
    h = wire.ResponseHeader(relocalization=FOUND if fits else NOT_FOUND, registrations=2,
                            candidates=1, server_us=50.0)
    h.place_scores[0] = score
    h.pose[:] = settled
    return ctypes.string_at(ctypes.byref(h), ctypes.sizeof(h))


def _ranked(a, b, c) -> kr.Ranked:
    """Scores over two tiles (t0 ranks 0, 1; t1 rank 0), in the search's order t0/0,
    t1/0, t0/1."""
    order = [("t0", 0), ("t1", 0), ("t0", 1)]
    answers = [("t0", _places([(a[0], a[1], 0), (c[0], c[1], 1)], 2)),
               ("t1", _places([(b[0], b[1], 0)], 1))]
    return kr.best_scored(order, answers)


def test_the_best_score_is_finished_and_judged_against_every_distinct_place():
    # The best score wins; equal scores go to the first in the search's order.
    r = _ranked((_at(0.0), 0.6), (_at(50.0), 0.8), (_at(90.0), 0.8))
    assert r.best == ("t1", 0)
    assert (r.candidates, r.registrations, r.scored_us) == (3, 6, 200.0)
    # A place far away within the margin: ambiguous.
    h = _header(kr.finish(_finished(_at(50.1, 1.0), 0.8, True), r, 1000.0))
    assert h.relocalization == AMBIGUOUS and list(h.place_scores) == [0.8, 0.8]
    assert (h.candidates, h.registrations, h.server_us) == (3, 8, 1250.0)
    # Every tile's scored places travel with the verdict, in the search's order, as one
    # server sends its scored places (as client/src/tiled.rs ``finish``).
    frame = kr.finish(_finished(_at(50.1, 1.0), 0.8, True), r, 1000.0)
    sent = np.frombuffer(frame[ctypes.sizeof(wire.ResponseHeader):], dtype=wire.PLACE_DTYPE)
    assert [float(p["translation"][0]) for p in sent] == [0.0, 50.0, 90.0]
    assert [float(p["score"]) for p in sent] == [0.6, 0.8, 0.8]
    assert [int(p["rank"]) for p in sent] == [0, 1, 2]
    # The same place settled from two proposals is no runner-up: found.
    r = _ranked((_at(0.0), 0.6), (_at(50.0), 0.8), (_at(50.3, 2.0), 0.79))
    h = _header(kr.finish(_finished(_at(50.0), 0.8, True), r, 0.0))
    assert h.relocalization == FOUND and list(h.place_scores) == [0.8, 0.6]
    # Turned more than DISTINCT_DEG it is another place: ambiguous.
    r = _ranked((_at(0.0), 0.1), (_at(50.0), 0.8), (_at(50.0, 10.0), 0.79))
    h = _header(kr.finish(_finished(_at(50.0), 0.8, True), r, 0.0))
    assert h.relocalization == AMBIGUOUS
    # The best place does not fit: not found.
    h = _header(kr.finish(_finished(_at(50.0), 0.8, False), r, 0.0))
    assert h.relocalization == NOT_FOUND
    # A refusal of a phase is the answer.
    refused = _places([], 0, code=wire.StatusCode.BUSY)
    assert kr.finish(refused, r, 0.0) == refused
    assert kr.best_scored([("t0", 0)], [("t0", refused)]) == refused
    # A place nobody chose is an error; nothing settled is not found.
    with pytest.raises(kfmap.TransportError, match="not chosen"):
        kr.best_scored([("t0", 0)], [("t0", _places([(_at(0.0), 0.5, 3)], 1))])
    none = kr.best_scored([("t0", 0)], [("t0", _places([], 1))])
    assert none.best is None
    h = _header(kr.nothing_settled(none, 10.0))
    assert h.relocalization == NOT_FOUND and (h.candidates, h.registrations) == (1, 2)


# -- tile sets: two emulated hosts against the merged map ----------------------------

TILE_PORTS = (17451, 17452)
#: The site's servers rank places otherwise than the defaults (their server.toml); the
#: gateways publish it with the index, and every client must rank as the servers do.
SITE_RANKING = kr.Ranking(keep_ratio=0.6, ambiguity_margin=0.2)


@dataclass
class TileSite:
    """A tile set served by two serve + gateway pairs, and its merged map served whole."""

    data: Path
    index: kr.TileIndex
    map_name: str
    endpoints: list[str]
    shares: list[list[str]]
    gateways: list[subprocess.Popen]
    oracle_name: str
    oracle_prefix: str
    tiles: Path


def _die_with_parent() -> None:
    """In the child: SIGKILL when pytest dies, so no host outlives an aborted run."""
    try:
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _start(args: list, log_path: Path, ready: str) -> subprocess.Popen:
    """Starts a kfmap process and waits for its ready line (stdout goes to ``log_path``
    with its stderr)."""
    log = open(log_path, "w")  # noqa: SIM115 - the draining thread keeps it
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=log, text=True,
                               preexec_fn=_die_with_parent)
    seen = threading.Event()

    def drain() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            log.flush()
            if line.startswith(ready):
                seen.set()
        log.close()

    threading.Thread(target=drain, daemon=True).start()
    if not seen.wait(READY_TIMEOUT_S) or process.poll() is not None:
        _stop(process)
        pytest.fail(f"{' '.join(map(str, args[:2]))} did not get ready; see {log_path}")
    return process


@pytest.fixture(scope="module")
def tile_site(kfmap_bin, tmp_path_factory):
    _require_namespace()
    out = tmp_path_factory.mktemp("kfmap-tiles")
    data, tiles = out / "sim", out / "court.tiles"
    run = dict(check=True, capture_output=True, text=True, timeout=300)
    # One lap of the courtyard's 24 m square at 8 m/s: 12 tiles of 10 m on the ring.
    subprocess.run([kfmap_bin, "simulate", "--preset", "courtyard", "--seconds", "12",
                    "--beams", "16", "--speed", "8", "--out", data], **run)
    subprocess.run([kfmap_bin, "bake", "--dataset", data, "--out", tiles, "--tile-size", "10",
                    "--halo", "10", "--keep-merged"], **run)
    index = kr.TileIndex.parse((tiles / "tiles.toml").read_text())
    # The cut gives each tile its search region: the tiles split a relocalization.
    assert index.shares_search
    assert not _index([(0, 0)], 10.0, 5.0).shares_search
    ids = [t.id for t in index.tiles]
    shares = [ids[0::2], ids[1::2]]
    base = os.environ.get("KFMAP_TEST_PREFIX") or f"kfpytest{os.getpid()}_"
    map_name = f"court-{os.getpid()}"
    processes: list[subprocess.Popen] = []
    prefixes = [f"{base}tiles{h}_" for h in range(len(shares))] + [f"{base}merged_"]

    def cleanup() -> None:
        for process in reversed(processes):
            _stop(process)
        for prefix in prefixes:
            remove_prefix_files(prefix)

    atexit.register(cleanup)
    # Every server of the site (and the merged map's) with the site's ranking.
    server_toml = out / "server.toml"
    server_toml.write_text(
        f"[relocalize]\nambiguity-margin = {SITE_RANKING.ambiguity_margin}\n\n"
        f"[relocalize.search]\nkeep-ratio = {SITE_RANKING.keep_ratio}\n"
    )
    try:
        gateways, endpoints = [], []
        # Every tile of a host searches at once on this machine's 2 cores: give them time.
        gateway_toml = out / "gateway.toml"
        gateway_toml.write_text("[gateway]\nrequest-timeout-s = 120.0\n")
        for h, share in enumerate(shares):
            only = ",".join(share)
            processes.append(_start(
                [kfmap_bin, "serve", "--tiles", tiles, "--map-name", map_name, "--only", only,
                 "--iceoryx-prefix", prefixes[h], "--config", server_toml],
                out / f"serve{h}.log", "ready:"))
            endpoints.append(f"tcp/127.0.0.1:{TILE_PORTS[h]}")
            gateways.append(_start(
                [kfmap_bin, "gateway", "--tiles", tiles, "--map-name", map_name, "--only", only,
                 "--iceoryx-prefix", prefixes[h], "--listen", endpoints[-1],
                 "--config", gateway_toml],
                out / f"gateway{h}.log", "ready: gateway"))
            processes.append(gateways[-1])
        oracle_name = f"{map_name}-merged"
        processes.append(_start(
            [kfmap_bin, "serve", "--map", tiles / "merged.kfmap", "--map-name", oracle_name,
             "--iceoryx-prefix", prefixes[-1], "--config", server_toml],
            out / "oracle.log", "ready:"))
        yield TileSite(data, index, map_name, endpoints, shares, gateways, oracle_name,
                       prefixes[-1], tiles)
    finally:
        cleanup()
        atexit.unregister(cleanup)


def _translation(pose: np.ndarray) -> np.ndarray:
    return np.asarray(pose[:3, 3], dtype=np.float64)


def test_a_tile_set_on_two_hosts_answers_as_the_merged_map(tile_site):
    site = tile_site
    truth = ground_truth(site.data)
    half_halo = site.index.halo / 2.0
    ids = [t.id for t in site.index.tiles]
    with kfmap.Client.remote(",".join(site.endpoints), site.map_name, timeout=120.0) as remote, \
            kfmap.Client(site.oracle_name, iceoryx_prefix=site.oracle_prefix,
                         timeout=30.0) as oracle:
        # The cut's index, with the servers' ranking as the gateways publish it.
        assert remote._conn.tile_index == dataclasses.replace(site.index, ranking=SITE_RANKING)
        assert remote.current_tile is None
        guess = previous = kfmap.pose_from_wire(truth[0, 1:])
        compared, crossings, worst_apart, worst_crossing = 0, 0, 0.0, 0.0
        last, seen, differ = None, set(), []
        # Bounded by its scans and each request's timeout (120 s remote, 30 s whole);
        # how long the drive takes is a benchmark's question, not this test's.
        for i in range(0, len(truth), 2):
            points, _ = scan_points(site.data, i)
            tiled = remote.localize(points, guess)
            tile = remote.current_tile
            whole = oracle.localize(points, guess)
            # The request went to a tile within the hysteresis of the guess.
            assert site.index.distance_to_core(ids.index(tile), guess[0, 3], guess[1, 3]) \
                <= half_halo, f"scan {i} on {tile}"
            apart = float(np.abs(tiled.pose - whole.pose).max())
            if apart > 1e-6 or tiled.status != whole.status:
                differ.append(f"scan {i} on {tile}: {apart:.2e} apart, {tiled.status.name} "
                              f"vs {whole.status.name}")
            worst_apart = max(worst_apart, apart)
            compared += 1
            seen.add(tile)
            if last is not None and tile != last:
                crossings += 1
                off = float(np.linalg.norm(_translation(tiled.pose) - truth[i, 1:4]))
                worst_crossing = max(worst_crossing, off)
                assert off < 0.05, f"scan {i}, {last} -> {tile}: {off} m from the truth"
            last = tile
            # Constant velocity: the next guess moves on as this scan moved.
            guess = tiled.pose @ np.linalg.inv(previous) @ tiled.pose
            previous = tiled.pose
        print(f"tiled drive: {compared} scans compared with the merged map, max difference "
              f"{worst_apart:.2e}; {crossings} tile changes over {len(seen)} tiles, worst "
              f"{worst_crossing * 100:.1f} cm from the truth at a crossing")
        assert crossings >= 4, f"only {crossings} tile changes"
        assert all(seen & set(share) for share in site.shares), seen  # both hosts answered

        # Relocalization asks every tile at once and ranks as one search of the merged map.
        for i in range(0, len(truth), len(truth) // 4):
            points, _ = scan_points(site.data, i)
            tiled = remote.relocalize(points)
            whole = oracle.relocalize(points)
            print(f"relocalize scan {i}: tiles {tiled.status.name} (score {tiled.score:.3f}, "
                  f"runner-up {tiled.runner_up:.3f}, {tiled.candidates} candidates), merged "
                  f"map {whole.status.name} (score {whole.score:.3f}, runner-up "
                  f"{whole.runner_up:.3f})")
            assert tiled.status == whole.status, f"scan {i}"
            # The same places scored alike: the verdict's margins are the merged map's.
            assert abs(tiled.score - whole.score) < 1e-9, f"scan {i}"
            assert abs(tiled.runner_up - whole.runner_up) < 1e-9, f"scan {i}"
            assert (tiled.pose is None) == (whole.pose is None), f"scan {i}"
            if tiled.pose is not None:
                apart = float(np.linalg.norm(_translation(tiled.pose) - _translation(whole.pose)))
                assert apart < 0.05, f"scan {i}: {apart} m from the merged map's"
    # Exactly one tile answered each scan, from the keyframes the whole map would use.
    assert not differ, f"{len(differ)} of {compared} answers differ: {differ}"


def test_the_rust_and_python_clients_rank_a_tile_set_as_its_servers(kfmap_bin, tile_site):
    """Relocalization over the tiles, by the Python client and by ``kfmap relocalize
    --remote`` (the Rust client) on the same scans: the same verdicts, scores and places,
    both ranked with the servers' settings (``SITE_RANKING``, published by the gateways
    with the index). The settings matter: some verdict differs from what the defaults
    would have said."""
    site = tile_site
    truth = ground_truth(site.data)
    picked = list(range(0, len(truth), len(truth) // 4))
    files = [site.data / "scans" / f"{i:06d}.pcd" for i in picked]
    with kfmap.Client.remote(",".join(site.endpoints), site.map_name, timeout=120.0) as remote:
        assert remote._conn.tile_index.ranking == SITE_RANKING
        python = [remote.relocalize(scan_points(site.data, i)[0]) for i in picked]
    out = subprocess.run(
        [kfmap_bin, "relocalize", "--remote", ",".join(site.endpoints), "--map-name",
         site.map_name, "--voxel", "0", "--timeout", "120", "--json", *files],
        capture_output=True, text=True, timeout=600,
    )
    assert out.returncode in (0, 1), out.stderr
    rust = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    assert len(rust) == len(picked), out.stdout
    by_defaults = 0
    for i, p, r in zip(picked, python, rust):
        status = p.status.name.lower().replace("_", "-")
        print(f"scan {i}: python {status} {p.score:.4f} / {p.runner_up:.4f}, "
              f"rust {r['status']} {r['score']:.4f} / {r['runner_up']:.4f}")
        assert status == r["status"], f"scan {i}"
        assert abs(p.score - r["score"]) < 1e-9, f"scan {i}"
        assert abs(p.runner_up - r["runner_up"]) < 1e-9, f"scan {i}"
        assert (p.pose is None) == (r["pose"] is None), f"scan {i}"
        if p.pose is not None:
            apart = float(np.linalg.norm(_translation(p.pose) - np.asarray(r["pose"][:3])))
            assert apart < 1e-4, f"scan {i}: {apart} m apart"
        # What the default margin would have said of the same fitting scores.
        if status in ("found", "ambiguous"):
            default_close = p.runner_up + kr.AMBIGUITY_MARGIN >= p.score
            if default_close != (status == "ambiguous"):
                by_defaults += 1
    assert by_defaults > 0, "the site's ranking decided nothing the defaults would not"
    print(f"{by_defaults} of {len(picked)} verdicts differ from the defaults'")


def _wait_for(ok, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if ok():
            return True
        time.sleep(0.01)
    return ok()


def test_a_tile_whose_hosts_are_gone_is_named_and_a_neighbour_stands_in(tile_site):
    """Runs last: it stops the gateways."""
    site = tile_site
    index, h = site.index, site.index.halo / 2.0
    ids = [t.id for t in index.tiles]
    points, _ = scan_points(site.data, 0)

    def guess_at(x: float, y: float) -> np.ndarray:
        pose = np.eye(4)
        pose[:2, 3] = [x, y]
        return pose

    def host0_within_h(x: float, y: float) -> bool:
        return any(index.distance_to_core(ids.index(u), x, y) <= h for u in site.shares[0])

    # Points in host 1's cores (a 1 m grid) with a host 0 tile within the hysteresis (it
    # stands in when host 1 is gone) and without (nothing may stand in).
    spots = [((t.col + fx) * index.tile_size, (t.row + fy) * index.tile_size, t.id)
             for t in index.tiles if t.id in site.shares[1]
             for fx in np.arange(0.05, 1.0, 0.1) for fy in np.arange(0.05, 1.0, 0.1)]
    near = [s for s in spots if host0_within_h(s[0], s[1])]
    alone = [s for s in spots if not host0_within_h(s[0], s[1])]
    assert near and alone, "both kinds of spot in this layout"
    with kfmap.Client.remote(",".join(site.endpoints), site.map_name, timeout=20.0) as remote:
        _stop(site.gateways[1])
        assert _wait_for(lambda: not remote._conn.alive_tiles & set(site.shares[1]))
        remote.localize(points, guess_at(*near[0][:2]))
        assert remote.current_tile in site.shares[0]
        with pytest.raises(kfmap.NoServerError, match=alone[0][2]):
            remote.localize(points, guess_at(*alone[0][:2]))
        # Relocalization asks the tiles still up.
        remote.relocalize(points)
        _stop(site.gateways[0])
        assert _wait_for(lambda: not remote._conn.alive_tiles)
        with pytest.raises(kfmap.NoServerError, match=near[0][2]):
            remote.localize(points, guess_at(*near[0][:2]))
        with pytest.raises(kfmap.NoServerError, match="no tile"):
            remote.relocalize(points)
