#!/usr/bin/env python3
"""KISS-ICP odometry anchor on ../shared/data/balm_os0 (install `kiss-icp small-gicp numpy`
in a venv outside the repository, e.g. `python3 -m venv /work/venv-anchors &&
/work/venv-anchors/bin/pip install kiss-icp small-gicp numpy`).

KISS-ICP's Python API (`kiss_icp.kiss_icp.KissICP`), voxel 0.5 m, no deskewing (the scans
are already deskewed), max range 100 m, otherwise its defaults. Writes the trajectory with
the dataset's timestamps (--out) and prints the aligned ATE against poses.txt.

`python kiss_icp_odometry.py [--start S] [--end E] [--step K] [--threads N] [--out est.tum]`
"""
import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP

from balm_pcd import run_odometry  # same folder


def make_estimator(threads):
    config = KISSConfig()
    config.data.deskew = False
    config.data.max_range = 100.0
    config.mapping.voxel_size = 0.5
    config.registration.max_num_threads = threads
    odometry = KissICP(config)

    def estimate(points):
        odometry.register_frame(points, np.array([]))
        return odometry.last_pose.copy()

    return estimate


if __name__ == "__main__":
    run_odometry("KISS-ICP", make_estimator)
