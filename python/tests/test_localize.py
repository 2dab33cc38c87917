"""Server-side localization and relocalization against the simulated ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

import kfmap
from _data import ground_truth, rotation_angle_deg, scan_points


def gt_in_map(client: kfmap.Client, dataset, index: int) -> np.ndarray:
    """Ground truth of scan ``index`` in the map frame (bake may have levelled it)."""
    return client.status().map_from_input @ kfmap.pose_from_wire(ground_truth(dataset)[index, 1:])


def perturbed(pose: np.ndarray, dx: float, dy: float, dyaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(dyaw_deg)), math.sin(math.radians(dyaw_deg))
    turn = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    out = pose @ turn
    out[:3, 3] += [dx, dy, 0.0]
    return out


@pytest.mark.parametrize("index", [5, 20])
def test_localize_converges_to_ground_truth(client, server, index: int) -> None:
    points, views = scan_points(server.dataset, index)
    truth = gt_in_map(client, server.dataset, index)
    guess = perturbed(truth, 0.3, -0.2, 3.0)
    assert np.linalg.norm(guess[:3, 3] - truth[:3, 3]) > 0.3
    found = client.localize(points, guess, view_dirs=views, stamp=index * 0.1)
    assert found.status == kfmap.TrackingStatus.OK, found.reason_names
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.03
    assert rotation_angle_deg(found.pose, truth) < 0.3
    assert found.inlier_ratio > 0.5 and found.converged and not found.degenerate
    assert found.iterations > 0 and found.registrations >= 1
    assert found.correction > 0.3  # it moved the guess about as far as we perturbed it
    assert found.covariance is not None and found.covariance.shape == (6, 6)
    assert np.allclose(found.covariance, found.covariance.T)
    np.testing.assert_allclose(found.pose[3], [0, 0, 0, 1])


def test_localize_from_nowhere_is_lost_and_keeps_the_guess(client, server) -> None:
    """A guess 40 m off, outside the map: no pose is adopted, the guess comes back."""
    points, _ = scan_points(server.dataset, 10)
    far = perturbed(gt_in_map(client, server.dataset, 10), 40.0, 40.0, 0.0)
    found = client.localize(points, far, max_iterations=10)
    assert found.status == kfmap.TrackingStatus.LOST
    assert found.inlier_ratio < 0.3 and "no-fit" in found.reason_names
    np.testing.assert_allclose(found.pose, far, atol=1e-9)


def test_relocalize_finds_the_scan_without_a_guess(client, server) -> None:
    index = 17
    points, views = scan_points(server.dataset, index)
    truth = gt_in_map(client, server.dataset, index)
    found = client.relocalize(points, view_dirs=views)
    assert isinstance(found.status, kfmap.RelocalizeStatus)
    assert found.candidates >= 1
    assert found.status == kfmap.RelocalizeStatus.FOUND, found
    assert found.pose is not None
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.1
    assert rotation_angle_deg(found.pose, truth) < 1.0
    assert found.score > found.runner_up and found.inlier_ratio > 0.5


def test_relocalize_with_a_tilt(client, server) -> None:
    """The levelled variant: the sensor's tilt given (here: level, as simulated)."""
    points, _ = scan_points(server.dataset, 8)
    truth = gt_in_map(client, server.dataset, 8)
    found = client.relocalize(points, tilt=np.eye(3))
    assert found.status == kfmap.RelocalizeStatus.FOUND, found
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.1
    assert rotation_angle_deg(found.pose, truth) < 1.0
