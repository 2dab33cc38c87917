#!/usr/bin/env python3
"""small_gicp odometry anchor on ../shared/data/balm_os0 (install `small-gicp numpy` in a
venv outside the repository, as for kiss_icp_odometry.py).

Replicates ScanToModelMatchingOdometry of small_gicp's src/example/kitti_odometry.py:
each scan is downsampled to 0.25 m voxels with covariances (k = 10), aligned (VGICP) to a
GaussianVoxelMap(1.0) with LRU horizon 100 / clear cycle 10, starting from the previous
pose times the previous motion (constant velocity), then inserted at its estimate.
Writes the trajectory with the dataset's timestamps (--out) and prints the aligned ATE.

`python small_gicp_odometry.py [--start S] [--end E] [--step K] [--threads N] [--out est.tum]`
"""
import numpy as np
import small_gicp

from balm_pcd import run_odometry  # same folder


def make_estimator(threads):
    target = small_gicp.GaussianVoxelMap(1.0)
    target.set_lru(horizon=100, clear_cycle=10)
    state = {"T_world_lidar": np.eye(4), "T_last_current": np.eye(4)}

    def estimate(points):
        downsampled, _ = small_gicp.preprocess_points(points, 0.25, num_threads=threads)
        if target.size() == 0:
            target.insert(downsampled)
            return state["T_world_lidar"].copy()
        guess = state["T_world_lidar"] @ state["T_last_current"]
        result = small_gicp.align(target, downsampled, guess, num_threads=threads)
        state["T_last_current"] = np.linalg.inv(state["T_world_lidar"]) @ result.T_target_source
        state["T_world_lidar"] = result.T_target_source
        target.insert(downsampled, result.T_target_source)
        return state["T_world_lidar"].copy()

    return estimate


if __name__ == "__main__":
    run_odometry("small_gicp", make_estimator)
