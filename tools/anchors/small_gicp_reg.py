#!/usr/bin/env python3
"""small_gicp registration anchor for `tests/integration/registration_real.rs` and `cargo bench -p
kfmap-geometry --bench registration` (install `small-gicp numpy` in a venv outside the
repository, as for small_gicp_cov.py).

1. KITTI 00 pairs 0-1 ... 4-5, 0.25 m voxels, identity guess: distance of the result
   from the ground-truth relative motion (poses_velo_kitti.txt).
2. small_gicp/{source,target}.ply (invalid returns filtered): preprocessing (0.25 m
   voxels + k = 10 covariances), GICP on the preprocessed clouds, and the whole
   registration from raw clouds, 1 and 2 threads; error against T_target_source.txt.
"""
import pathlib

import numpy as np
import small_gicp

from small_gicp_cov import median_ms, read_ply_xyz  # same folder
from small_gicp_knn import poses, scan

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "small_gicp"


def error(T, truth):
    d = np.linalg.inv(truth) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return np.linalg.norm(d[:3, 3]) * 100, angle


def valid(points):
    return points[np.any(points != 0, axis=1)]


def main():
    gt = poses()
    for i in range(5):
        truth = np.linalg.inv(gt[i]) @ gt[i + 1]
        result = small_gicp.align(scan(i), scan(i + 1), downsampling_resolution=0.25, num_threads=1)
        cm, deg = error(result.T_target_source, truth)
        print(f"kitti00 {i}-{i + 1}: {cm:.3f} cm, {deg:.4f} deg, {result.iterations} iterations")

    target = valid(read_ply_xyz(DATA / "target.ply"))
    source = valid(read_ply_xyz(DATA / "source.ply"))
    truth = np.loadtxt(DATA / "T_target_source.txt")
    for threads in (1, 2):
        pre = lambda: (
            small_gicp.preprocess_points(target, 0.25, num_neighbors=10, num_threads=threads),
            small_gicp.preprocess_points(source, 0.25, num_neighbors=10, num_threads=threads),
        )
        (t, t_tree), (s, _) = pre()
        result = small_gicp.align(t, s, t_tree, num_threads=threads)
        cm, deg = error(result.T_target_source, truth)
        raw = small_gicp.align(target, source, downsampling_resolution=0.25, num_threads=threads)
        raw_cm, raw_deg = error(raw.T_target_source, truth)
        print(f"{threads} thread(s): from raw clouds {raw_cm:.3f} cm, {raw_deg:.4f} deg; preprocess {median_ms(pre):.2f} ms, "
              f"gicp {median_ms(lambda: small_gicp.align(t, s, t_tree, num_threads=threads)):.2f} ms, "
              f"whole {median_ms(lambda: small_gicp.align(target, source, downsampling_resolution=0.25, num_threads=threads)):.2f} ms; "
              f"{cm:.2f} cm, {deg:.3f} deg from T_target_source.txt, {len(t.points())} / {len(s.points())} points")


if __name__ == "__main__":
    main()
