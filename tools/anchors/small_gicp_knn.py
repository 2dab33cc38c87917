#!/usr/bin/env python3
"""small_gicp KD-tree anchor for `cargo bench -p kfmap-geometry --bench kdtree` (install
`small-gicp numpy` in a venv outside the repository, as for small_gicp_cov.py).

KITTI 00: tree over frame 0, queries = frame 1 moved into frame 0 by the ground-truth
poses; one thread; build, 1-NN and k = 20 for all queries, in scan and Morton order.
"""
import pathlib
import time

import numpy as np
import small_gicp

from small_gicp_cov import median_ms  # same folder

KITTI = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "kitti00"


def scan(i):
    return np.fromfile(KITTI / f"{i:06d}.bin", dtype="<f4").reshape(-1, 4)[:, :3].astype(np.float64)


def poses():
    rows = np.loadtxt(KITTI / "poses_velo_kitti.txt")
    out = []
    for r in rows:
        m = np.eye(4)
        m[:3, :] = r.reshape(3, 4)
        out.append(m)
    return out


def morton(points):
    lo, hi = points.min(axis=0), points.max(axis=0)
    cells = ((points - lo) / np.maximum(hi - lo, 1e-300) * (2**21 - 1)).astype(np.uint64)
    key = np.zeros(len(points), dtype=np.uint64)
    for bit in range(21):
        for axis in range(3):
            key |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(key, kind="stable")


def main():
    p = poses()
    target = scan(0)
    rel = np.linalg.inv(p[0]) @ p[1]
    src = scan(1)
    queries = src @ rel[:3, :3].T + rel[:3, 3]
    sorted_queries = queries[morton(queries)]
    print(f"tree {len(target)} points, {len(queries)} queries, 1 thread")
    print(f"build      {median_ms(lambda: small_gicp.KdTree(target, num_threads=1)):8.1f} ms")
    tree = small_gicp.KdTree(target, num_threads=1)
    for label, q in (("scan", queries), ("morton", sorted_queries)):
        nn = median_ms(lambda: tree.batch_nearest_neighbor_search(q, num_threads=1))
        knn = median_ms(lambda: tree.batch_knn_search(q, 20, num_threads=1), repeats=7)
        print(f"{label:7s} 1-NN {nn:8.1f} ms   k=20 {knn:8.1f} ms")


if __name__ == "__main__":
    main()
