#!/usr/bin/env python3
"""Anchor figures from small_gicp (PyPI `small-gicp`), for side-by-side comparison with
`cargo bench -p kfmap-geometry --bench geometry`. Not a dependency of kfmap: install it in a venv outside
the repository, e.g. `python3 -m venv /tmp/anchors && /tmp/anchors/bin/pip install
small-gicp numpy`, then run `/tmp/anchors/bin/python tools/anchors/small_gicp_cov.py`.

Measures on ../shared/data/small_gicp/target.ply, with and without the ~5 000 invalid
points at (0,0,0): KD-tree build, estimate_covariances (k = 20), voxel downsampling
(0.25 m), on 1 and 2 threads; median of repeated runs.
"""
import pathlib
import time

import numpy as np
import small_gicp

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "small_gicp" / "target.ply"


def read_ply_xyz(path):
    raw = path.read_bytes()
    start = raw.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(raw[start:], dtype="<f4").reshape(-1, 4)[:, :3].astype(np.float64)


def median_ms(fn, repeats=30):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def main():
    all_points = read_ply_xyz(DATA)
    valid = all_points[np.linalg.norm(all_points, axis=1) >= 0.1]
    for label, pts in (("filtered", valid), ("unfiltered", all_points)):
        n = len(pts)
        for threads in (1, 2):
            cloud = small_gicp.PointCloud(pts)
            build = median_ms(lambda: small_gicp.KdTree(cloud, num_threads=threads))
            tree = small_gicp.KdTree(cloud, num_threads=threads)
            cov = median_ms(lambda: small_gicp.estimate_covariances(cloud, tree, num_neighbors=20, num_threads=threads))
            vox = median_ms(lambda: small_gicp.voxelgrid_sampling(cloud, 0.25, num_threads=threads))
            print(f"{label:10s} n={n} threads={threads}: kdtree {build:.1f} ms, "
                  f"covariances {cov:.1f} ms ({n / cov / 1e3:.2f} M pts/s), voxel 0.25 {vox:.2f} ms")


if __name__ == "__main__":
    main()
