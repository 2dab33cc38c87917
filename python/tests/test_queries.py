"""nearest / radius / cov2cov against the ``kfmap query`` CLI (the Rust client) on the
same points and pose, and against brute force over the map points found."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import kfmap
from _data import cli_query, euler_wire, ground_truth, scan_points, transform, write_xyz_bin, yaw_deg

SCAN = 12
FIELDS = ("query", "keyframe", "local_index", "point", "dist_sq", "information")


@pytest.fixture(scope="module")
def probe(server, tmp_path_factory):
    """A thinned scan (every 37th point farther than 1 m: the CLI's load filter keeps
    them all), its file for the CLI, and the ground-truth pose as the CLI spells it."""
    points, _ = scan_points(server.dataset, SCAN)
    far = points[np.linalg.norm(points, axis=1) > 1.0][::37]
    path = write_xyz_bin(tmp_path_factory.mktemp("probe") / "probe.bin", far)
    x, y, z, *quat = (float(v) for v in ground_truth(server.dataset)[SCAN, 1:])
    yaw = yaw_deg(np.array(quat))
    text = f"{x!r} {y!r} {z!r} 0 0 {yaw!r}"
    return far, path, text, euler_wire(x, y, z, 0.0, 0.0, yaw)


def sort_answer(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.lexsort((arrays["local_index"], arrays["keyframe"], arrays["query"]))
    return {name: arrays[name][order] for name in FIELDS}


def as_dict(pairings: kfmap.Pairings) -> dict[str, np.ndarray]:
    return {name: getattr(pairings, name) for name in FIELDS}


def assert_identical(ours: kfmap.Pairings, cli: dict[str, np.ndarray]) -> None:
    a, b = sort_answer(as_dict(ours)), sort_answer(cli)
    assert len(ours) == len(cli["query"])
    for name in FIELDS:
        assert a[name].dtype == b[name].dtype, name
        # Bit for bit: the CLI prints every float in its shortest exact form.
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.mark.parametrize("k", [1, 3])
def test_nearest_matches_cli(client, server, probe, tmp_path: Path, k: int) -> None:
    points, path, text, pose = probe
    ours = client.nearest(points, pose, k=k)
    assert len(ours) == k * len(points)
    assert ours.point.shape == (len(ours), 3) and ours.point.dtype == np.float32
    assert not ours.information.any()
    cli = cli_query(server, path, text, "nearest", tmp_path / "n.csv", "--k", str(k))
    assert_identical(ours, cli)


def test_nearest_around_matches_cli_and_the_active_set(
    client, server, probe, tmp_path: Path
) -> None:
    points, path, text, pose = probe
    ours = client.nearest(points, pose, keyframes=2)
    assert len(ours) == len(points) and len(ours.active) == 2
    cli = cli_query(server, path, text, "nearest", tmp_path / "n2.csv", "--keyframes", "2")
    assert_identical(ours, cli)
    # On this 3-keyframe map the active set is all of it: 2 keyframes never find a
    # nearer point, and the one left out held some points' nearest (the Rust test
    # checks the answer against brute force).
    everything = client.nearest(points, pose, k=1)
    assert set(ours.active.tolist()) < set(everything.active.tolist())
    assert np.all(ours.dist_sq >= everything.dist_sq)
    assert np.any(ours.dist_sq > everything.dist_sq)


def test_bounded_nearest_is_the_unbounded_within_the_bound_and_matches_cli(
    client, server, probe, tmp_path: Path
) -> None:
    points, path, text, pose = probe
    everything = client.nearest(points, pose, k=1)
    ours = client.nearest(points, pose, k=1, max_dist=0.05)
    near = everything.dist_sq <= np.float32(0.05) ** 2
    assert 0 < len(ours) < len(everything)
    assert np.array_equal(ours.query, everything.query[near])
    assert np.array_equal(ours.dist_sq, everything.dist_sq[near])
    cli = cli_query(server, path, text, "nearest", tmp_path / "nb.csv", "--max-dist", "0.05")
    assert_identical(ours, cli)
    for bad in (-1.0, 0.0, 25.0, float("nan")):
        with pytest.raises(kfmap.InvalidArgument, match="max_dist"):
            client.nearest(points, pose, max_dist=bad)


def test_radius_matches_cli(client, server, probe, tmp_path: Path) -> None:
    points, path, text, pose = probe
    ours = client.radius(points, pose, r=0.4)
    assert len(ours) > len(points)  # a dense map: several points per query
    assert ours.dist_sq.max() <= np.float32(0.4) ** 2 * (1 + 1e-5)
    cli = cli_query(server, path, text, "radius", tmp_path / "r.csv", "--radius", "0.4")
    assert_identical(ours, cli)


def test_cov2cov_matches_cli(client, server, probe, tmp_path: Path) -> None:
    points, path, text, pose = probe
    ours = client.cov2cov(points, pose, max_pair_dist=1.0)
    assert 0 < len(ours) <= len(points)
    assert np.all(np.diff(ours.query.astype(np.int64)) > 0)  # one per point, query order
    assert ours.information.any() and len(ours.active) > 0
    infos = ours.information_matrices()
    assert np.all(np.linalg.eigvalsh(infos) > 0)  # information matrices are SPD
    cli = cli_query(server, path, text, "cov2cov", tmp_path / "c.csv", "--max-pair-dist", "1")
    assert_identical(ours, cli)


def test_nearest_is_the_closest_of_the_radius_answer(client, probe) -> None:
    """Brute force: over the map points a radius query finds, the closest one is the
    nearest answer, and every reported squared distance is the true one."""
    points, _, _, pose = probe
    r = 0.5
    near = client.nearest(points, pose, k=1)
    around = client.radius(points, pose, r=r)
    moved = transform(kfmap.pose_from_wire(pose), points)
    for answer in (near, around):
        true = np.sum((moved[answer.query] - answer.point) ** 2, axis=1)
        np.testing.assert_allclose(answer.dist_sq, true, rtol=1e-4, atol=1e-6)
    for q in np.unique(around.query):
        found = around.query == q
        best = np.argmin(around.dist_sq[found])
        i = int(np.flatnonzero(near.query == q)[0])
        assert near.dist_sq[i] == pytest.approx(around.dist_sq[found][best], rel=1e-5, abs=1e-9)
    # Points with nothing within r have their nearest map point farther than r.
    lonely = np.setdiff1d(near.query, around.query)
    assert np.all(near.dist_sq[np.isin(near.query, lonely)] > np.float32(r * r) * (1 - 1e-5))


def test_float64_points_and_matrix_pose_give_the_same_answer(client, probe) -> None:
    points, _, _, pose = probe
    as32 = client.nearest(points, pose)
    as64 = client.nearest(points.astype(np.float64), kfmap.pose_from_wire(pose))
    np.testing.assert_array_equal(as32.local_index, as64.local_index)
    np.testing.assert_allclose(as32.dist_sq, as64.dist_sq, rtol=1e-4, atol=1e-6)


def test_echo_counts_points(client) -> None:
    assert client.echo(np.zeros((17, 3), np.float32)) == 17
