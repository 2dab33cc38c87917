#!/usr/bin/env python3
"""KISS-ICP odometry anchor on a drive stored as a kfmap dataset folder of binary PCD scans
(`scans/*.pcd` with float32 x y z first, `poses.txt` in TUM): ../shared/data/kitti00_drive
once its `extract.sh` has written the scans (kept outside this repository). Install
`kiss-icp numpy` in a venv outside the repository (see kiss_icp_odometry.py).

KISS-ICP 1.3's Python API, max range 100 m, voxel 1.0 m (its default for that range),
otherwise its defaults; no deskew (these scans carry no per-point times, and KISS-ICP 1.3
deskews only scans that do). The scans are taken as they are: no KITTI vertical-angle
correction (--kitti-correction applies KISS-ICP's 0.205 deg one, for comparison only).

Writes the estimate as TUM (--out) with poses.txt's stamps, prints the odometry loop's
wall time; errors come from kitti_drift.py (aligned ATE and KITTI-style drift).

`python kiss_icp_drive.py --dataset D --out est.tum [--voxel V] [--threads N] [--kitti-correction]`
"""
import argparse
import pathlib
import time

import numpy as np

from ate import read_tum, write_tum


def read_pcd_xyz(path):
    """x y z (N, 3) of a binary PCD whose first three fields are float32 x y z."""
    data = path.read_bytes()
    offset, count, fields, sizes, types = 0, None, None, None, None
    while True:
        end = data.index(b"\n", offset)
        words = data[offset:end].decode("ascii").split()
        offset = end + 1
        if not words:
            continue
        key = words[0].upper()
        if key == "FIELDS":
            fields = words[1:]
        elif key == "SIZE":
            sizes = [int(s) for s in words[1:]]
        elif key == "TYPE":
            types = words[1:]
        elif key == "POINTS":
            count = int(words[1])
        elif key == "DATA":
            if words[1] != "binary":
                raise SystemExit(f"{path}: DATA {words[1]}, only binary PCD is read here")
            break
    if fields[:3] != ["x", "y", "z"] or sizes[:3] != [4, 4, 4] or types[:3] != ["F", "F", "F"]:
        raise SystemExit(f"{path}: the first fields are not float32 x y z ({fields})")
    stride = sum(sizes)
    rows = np.frombuffer(data, dtype=np.uint8, count=count * stride, offset=offset).reshape(count, stride)
    xyz = rows[:, :12].copy().view(np.float32).reshape(count, 3)
    return xyz[np.isfinite(xyz).all(axis=1)].astype(np.float64)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=pathlib.Path, required=True)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--voxel", type=float, default=1.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--kitti-correction", action="store_true")
    args = parser.parse_args()
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.pybind import kiss_icp_pybind

    times, _ = read_tum(args.dataset / "poses.txt")
    paths = sorted((args.dataset / "scans").glob("*.pcd"))
    if len(paths) != len(times):
        raise SystemExit(f"{len(paths)} scans but {len(times)} poses in {args.dataset}")
    config = KISSConfig()
    config.data.deskew = False
    config.data.max_range = 100.0
    config.mapping.voxel_size = args.voxel
    config.registration.max_num_threads = args.threads
    odometry = KissICP(config)
    poses = []
    started = time.time()
    for path in paths:
        points = read_pcd_xyz(path)
        if args.kitti_correction:
            points = np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(points)))
        odometry.register_frame(points, np.array([]))
        poses.append(odometry.last_pose.copy())
    seconds = time.time() - started
    write_tum(args.out, times, np.array(poses))
    print(f"KISS-ICP on {len(paths)} scans (voxel {args.voxel} m, {args.threads} threads): {seconds:.1f} s -> {args.out}")


if __name__ == "__main__":
    main()
