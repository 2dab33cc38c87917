"""status() against ``kfmap status`` / ``kfmap inspect``, and push_imu_window()."""

from __future__ import annotations

import json
import math
import re
import subprocess

import numpy as np

import kfmap
from _data import ground_truth, imu_samples


def cli_json(server, *args: str) -> dict:
    done = subprocess.run([server.bin, *args, "--json"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_status_matches_the_map_and_the_cli(client, server) -> None:
    ours = client.status()
    inspected = cli_json(server, "inspect", str(server.map_path))
    assert ours.map_name == server.map_name
    assert (ours.keyframes, ours.points) == (inspected["keyframes"], inspected["points"])
    cli = cli_json(server, "status", "--map-name", server.map_name,
                   "--iceoryx-prefix", server.prefix)
    assert (cli["map_name"], cli["keyframes"], cli["points"], cli["map_path"]) == (
        ours.map_name, ours.keyframes, ours.points, ours.map_path)
    assert ours.uptime_s > 0 and cli["uptime_s"] >= ours.uptime_s
    for kind, stats in ours.kinds.items():  # the CLI asked later: at least as many
        assert cli["requests"][kind]["count"] >= stats.count
    rotation = ours.map_from_input[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)


def test_status_counts_grow_with_requests(client) -> None:
    before = client.status()
    points = np.random.default_rng(3).uniform(-5, 5, (50, 3)).astype(np.float32)
    for _ in range(3):
        client.nearest(points, k=2)
    client.radius(points, r=0.2)
    after = client.status()
    count = lambda report, kind: report.kinds[kind].count if kind in report.kinds else 0  # noqa: E731
    assert count(after, "nearest") >= count(before, "nearest") + 3
    assert count(after, "radius") >= count(before, "radius") + 1
    assert count(after, "status") >= count(before, "status") + 1
    assert after.kinds["nearest"].p99_us >= after.kinds["nearest"].p50_us > 0
    assert after.uptime_s > before.uptime_s
    assert after.sessions >= 1
    assert client.client_node in {s.client for s in after.session_gravity}


def test_push_imu_window_pools_the_dataset_imu(client, server) -> None:
    """Windows of imu.csv between every other scan (unstamped: raw means) fill the
    session's pool; from 10 members on the server gives gravity, which must point
    along the simulated gravity (meta.toml), within the platform's acceleration."""
    gt = ground_truth(server.dataset)
    imu = imu_samples(server.dataset)
    meta = (server.dataset / "meta.toml").read_text()
    found = re.search(r"^gravity-map = \[([^\]]*)\]", meta, re.MULTILINE)
    assert found, "meta.toml has no gravity-map"
    down = np.array([float(v) for v in found.group(1).split(",")])
    previous, answer = gt[0, 0], None
    for n, i in enumerate(range(2, len(gt), 2), start=1):
        window = imu[(imu[:, 0] > previous) & (imu[:, 0] <= gt[i, 0])]
        previous = gt[i, 0]
        answer = client.push_imu_window(i, kfmap.pose_from_wire(gt[i, 1:]), window)
        assert answer.members == n
        assert (answer.gravity is None) == (n < 10)
    assert answer is not None and answer.gravity is not None
    angle = math.degrees(math.acos(abs(answer.gravity @ down)
                                   / np.linalg.norm(answer.gravity) / np.linalg.norm(down)))
    assert angle < 5.0
    assert abs(np.linalg.norm(answer.gravity) - np.linalg.norm(down)) < 0.3
    assert answer.inliers <= answer.members and answer.correction.shape == (4,)
    pools = {s.client: s.pool for s in client.status().session_gravity}
    assert pools[client.client_node].members == answer.members


def test_push_imu_window_with_stamp_waits_for_poses(client, server) -> None:
    """A stamped window without stamped poses around it is not pooled as a raw mean."""
    gt = ground_truth(server.dataset)
    imu = imu_samples(server.dataset)
    window = imu[(imu[:, 0] > gt[3, 0]) & (imu[:, 0] <= gt[5, 0])]
    answer = client.push_imu_window(5, kfmap.pose_from_wire(gt[5, 1:]), window,
                                    stamp=float(gt[5, 0]))
    assert answer.members == 0 and answer.gravity is None
    assert answer.pending + answer.skipped == 1
