"""Errors: bad input is refused before sending, server refusals carry their status,
no server and timeouts are their own exceptions."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

import kfmap
from kfmap.transport import MAX_CLIENTS_PER_PROCESS

GOOD = np.zeros((4, 3), np.float32) + [1.0, 2.0, 0.5]


def requests_served(client: kfmap.Client) -> int:
    """Requests of every kind but status (the status request itself counts) the
    server has answered."""
    return sum(s.count for kind, s in client.status().kinds.items() if kind != "status")


@pytest.mark.parametrize(
    "call",
    [
        lambda c: c.nearest(np.zeros((5, 2), np.float32)),
        lambda c: c.nearest(np.zeros((5, 3, 1), np.float32)),
        lambda c: c.nearest(np.zeros(3, np.float32)),
        lambda c: c.nearest(np.zeros((5, 3), np.int32)),
        lambda c: c.nearest(np.zeros((5, 3), np.float16)),
        lambda c: c.nearest(np.array([["a", "b", "c"]])),
        lambda c: c.nearest(GOOD, k=-1),
        lambda c: c.nearest(GOOD, k=1.5),
        lambda c: c.nearest(GOOD, np.eye(3)),
        lambda c: c.nearest(GOOD, np.diag([1.0, 2.0, 1.0, 1.0])),
        lambda c: c.nearest(GOOD, [0, 0, 0, 0, 0, 0, 2.0]),
        lambda c: c.radius(GOOD, r="wide"),
        lambda c: c.cov2cov(GOOD, None, view_dirs=np.zeros((3, 3), np.float32)),
        lambda c: c.cov2cov(GOOD, None, covariances=np.zeros((4, 3), np.float32)),
        lambda c: c.cov2cov(GOOD, None, mode="sloppy"),
        lambda c: c.localize(GOOD, np.full((4, 4), np.nan)),
        lambda c: c.push_imu_window(0, None, np.zeros((5, 6))),
        lambda c: c.push_imu_window(-1, None, np.zeros((5, 7))),
    ],
)
def test_bad_input_raises_value_error_before_sending(client, call) -> None:
    before = requests_served(client)
    with pytest.raises(ValueError) as caught:
        call(client)
    assert isinstance(caught.value, kfmap.KfmapError)
    assert str(caught.value)
    assert requests_served(client) == before  # nothing reached the server


@pytest.mark.parametrize(
    "call, status",
    [
        (lambda c: c.nearest(GOOD, k=65), kfmap.StatusCode.BAD_REQUEST),  # MAX_K = 64
        (lambda c: c.nearest(GOOD, k=0), kfmap.StatusCode.BAD_REQUEST),
        (lambda c: c.nearest(GOOD, keyframes=65), kfmap.StatusCode.BAD_REQUEST),  # MAX_KEYFRAMES
        (lambda c: c.radius(GOOD, r=25.0), kfmap.StatusCode.BAD_REQUEST),  # MAX_RADIUS
        (lambda c: c.radius(GOOD, r=-1.0), kfmap.StatusCode.BAD_REQUEST),
        (lambda c: c.cov2cov(GOOD, max_pair_dist=80.0), kfmap.StatusCode.BAD_REQUEST),
        (lambda c: c.nearest(np.zeros((0, 3), np.float32)), kfmap.StatusCode.EMPTY_SCAN),
        (lambda c: c.push_imu_window(0, None, np.zeros((0, 7))), kfmap.StatusCode.EMPTY_SCAN),
    ],
)
def test_server_refusals_carry_the_status(client, call, status) -> None:
    with pytest.raises(kfmap.ServerError) as caught:
        call(client)
    e = caught.value
    assert e.status == status and e.code == int(status)
    assert e.status_name == status.wire_name and e.message
    assert e.status_name in str(e) and e.message in str(e)


def test_huge_radius_is_too_large(client) -> None:
    """20 m around a point of a dense map finds more than max-radius-points (4096)."""
    with pytest.raises(kfmap.ServerError) as caught:
        client.radius(GOOD, r=20.0)
    assert caught.value.status == kfmap.StatusCode.TOO_LARGE
    assert "max-radius-points" in caught.value.message


def test_non_finite_point_is_located(client) -> None:
    points = np.tile(GOOD[:1], (10, 1))
    points[6, 1] = np.nan
    with pytest.raises(kfmap.ServerError) as caught:
        client.nearest(points)
    assert caught.value.status == kfmap.StatusCode.NON_FINITE_POINT
    assert caught.value.detail == 6


def test_client_still_works_after_refusals(client) -> None:
    with pytest.raises(kfmap.ServerError):
        client.nearest(GOOD, k=1000)
    assert len(client.nearest(GOOD, k=2)) == 8


def test_no_server_is_reported_quickly(server) -> None:
    started = time.monotonic()
    with pytest.raises(kfmap.NoServerError) as caught:
        kfmap.Client("nonexistent", iceoryx_prefix=server.prefix)
    assert time.monotonic() - started < 2.0
    assert "nonexistent" in str(caught.value)
    assert not isinstance(caught.value, (kfmap.RequestTimeout, kfmap.ServerError))


def _wait_until_stopped(pid: int, limit_s: float = 10.0) -> None:
    """Waits until every thread of ``pid`` is stopped: SIGSTOP takes effect when each
    thread is next scheduled, so on a loaded machine one may still answer a request sent
    right after ``kill`` returns."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        states = []
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                stat = (task / "stat").read_text()
            except OSError:
                continue  # a thread that just ended
            states.append(stat.rsplit(")", 1)[1].split()[0])
        if states and all(state in ("T", "t") for state in states):
            return
        time.sleep(0.005)
    raise AssertionError(f"process {pid} not stopped {limit_s} s after SIGSTOP")


def test_timeout_is_its_own_error_and_the_client_reconnects(server) -> None:
    with kfmap.Client(server.map_name, iceoryx_prefix=server.prefix, timeout=0.5) as c:
        c.status()
        os.kill(server.process.pid, signal.SIGSTOP)
        try:
            _wait_until_stopped(server.process.pid)
            started = time.monotonic()
            with pytest.raises(kfmap.RequestTimeout) as caught:
                c.status()
            assert 0.45 < time.monotonic() - started < 3.0
            assert isinstance(caught.value, TimeoutError)
        finally:
            os.kill(server.process.pid, signal.SIGCONT)
        c.timeout = 30.0
        assert c.status().map_name == server.map_name


def test_one_process_opens_at_most_16_clients(server) -> None:
    clients = []
    try:
        for _ in range(MAX_CLIENTS_PER_PROCESS):
            clients.append(kfmap.Client(server.map_name, iceoryx_prefix=server.prefix))
        with pytest.raises(kfmap.TooManyClientsError):
            kfmap.Client(server.map_name, iceoryx_prefix=server.prefix)
        clients.pop().close()
        clients.append(kfmap.Client(server.map_name, iceoryx_prefix=server.prefix))
    finally:
        for c in clients:
            c.close()


def test_closed_client_refuses_calls(server) -> None:
    c = kfmap.Client(server.map_name, iceoryx_prefix=server.prefix)
    c.close()
    c.close()  # idempotent
    with pytest.raises(kfmap.KfmapError):
        c.status()


def test_bad_names_and_timeouts_are_value_errors() -> None:
    with pytest.raises(ValueError):
        kfmap.Client("")
    with pytest.raises(ValueError):
        kfmap.Client("x", iceoryx_prefix="bad/prefix", timeout=1.0)
    with pytest.raises(ValueError):
        kfmap.Client("x", timeout=0)
