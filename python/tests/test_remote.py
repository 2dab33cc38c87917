"""``Client.remote`` through a ``kfmap gateway`` (Zenoh over TCP) against the session's
test server, checked against the local client (iceoryx2) on the same server: every
remote answer must equal its local twin.

Network tests run only inside a private network namespace (``unshare -rn``: only ``lo``
exists), which ``run_tests.sh`` creates for this file and marks with
``KFMAP_TEST_NETNS=1``; elsewhere they skip (and fail under ``CI=true``).
"""

from __future__ import annotations

import os
import subprocess
import threading

import numpy as np
import pytest

import kfmap
from _data import ground_truth, scan_points

ENDPOINT = "tcp/127.0.0.1:17449"


def _in_namespace() -> bool:
    return os.environ.get("KFMAP_TEST_NETNS") == "1"


@pytest.fixture(scope="module")
def gateway(kfmap_bin, server):
    if not _in_namespace():
        reason = "remote tests run only in the network namespace run_tests.sh creates"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{reason}, and CI=true: run them through python/run_tests.sh")
        pytest.skip(reason)
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    assert [l.split(":")[1].strip() for l in links.splitlines()] == ["lo"], links
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
