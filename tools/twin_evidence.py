#!/usr/bin/env python3
"""What tells a simulated site from its turned twins, scan by scan: offline, from the
simulator's files and poses only (no kfmap code), at the true pose and at the true pose
turned about a vertical axis (the courtyard's square of walls maps onto itself every
90 degrees).

    tools/twin_evidence.py MAP_DATASET RUN_DATASET [--scans N] [--min-z M] [--center X,Y]

MAP_DATASET is the map's day (`kfmap simulate ... --seed 41 --out map`), RUN_DATASET a
later recording of the same route (`--seed 42`); both are read as the simulator wrote
them (scans/*.pcd, poses_gt.txt in the site's frame). The map is every 5th scan of the
map's day at its true pose, on 0.1 m voxels, as a baked map holds it. For every second
scan of the first N (default 30) it prints, per hypothesis (the truth, turned 90, 180
and 270 degrees about --center, default the origin):
- *explained*: the share of the scan's points at least --min-z (default 1 m) above
  the flat floor with a map point within 0.3 m, the scan on 0.25 m voxels as `kfmap
  localize` sends it: the scan-to-map evidence the tracker's `explained` measures (its
  tight distance at the default 1 m pairing distance; on the raw scan the near field's
  density would outweigh the rest);
- *contradicted*: map-to-scan evidence, which `explained` cannot see: the map's points
  at least --min-z high within 40 m are drawn into the scan's range image (a 64-beam
  sensor from -24.9 to +2 deg, 0.2 deg columns, as the simulator's default); of the
  pixels where the map predicts a surface and the scan either returns within 0.5 m of
  it (confirmed) or sees past it or nothing (contradicted), the contradicted share.
  A nearer return is an occlusion and counts as neither.
Needs numpy and scipy. Flat floors only (the courtyard, the corridor).
"""
import argparse
import pathlib
import sys

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / "anchors"))
from ate import read_tum  # noqa: E402  (the anchors' TUM reader)
from balm_pcd import read_pcd  # noqa: E402  (the anchors' binary PCD reader)

# The simulator's default 64-beam sensor (sim/src/lidar.rs).
EL_LOW_DEG, EL_HIGH_DEG, BEAMS, AZ_RES_DEG = -24.9, 2.0, 64, 0.2
EL_STEP_DEG = (EL_HIGH_DEG - EL_LOW_DEG) / (BEAMS - 1)
COLUMNS = int(round(360 / AZ_RES_DEG))
RANGE_M = 40.0
EXPLAINED_M = 0.3
AGREE_M = 0.5
# `kfmap localize --voxel`'s default: the scan as the tracker measures it.
SENT_VOXEL_M = 0.25


def voxelized(points, size):
    keys = np.floor(points / size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[first]


def turn_about(center, deg):
    """4x4 rotation by `deg` about the vertical through `center` (x, y)."""
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:2, 3] = center - T[:2, :2] @ center
    return T


def range_image(local):
    """The nearest range per pixel of points in the sensor frame (inf: no return)."""
    ranges = np.linalg.norm(local, axis=1)
    azimuth = np.degrees(np.arctan2(local[:, 1], local[:, 0])) % 360
    elevation = np.degrees(np.arcsin(np.clip(local[:, 2] / np.maximum(ranges, 1e-9), -1, 1)))
    row = np.round((elevation - EL_LOW_DEG) / EL_STEP_DEG).astype(int)
    column = np.round(azimuth / AZ_RES_DEG).astype(int) % COLUMNS
    inside = (row >= 0) & (row < BEAMS)
    image = np.full((BEAMS, COLUMNS), np.inf)
    np.minimum.at(image, (row[inside], column[inside]), ranges[inside])
    return image


def evidence(scan, sent, T, world_tree, high_map, min_z):
    """(explained, contradicted) at pose `T` (4x4) of a scan (sensor frame): `sent` (on
    the voxels the tracker receives) explained, the whole `scan` seeing past the map."""
    R, t = T[:3, :3], T[:3, 3]
    in_map = sent @ R.T + t
    high = in_map[:, 2] >= min_z
    distance, _ = world_tree.query(in_map[high], distance_upper_bound=EXPLAINED_M)
    explained = float(np.mean(np.isfinite(distance))) if high.any() else float("nan")
    local = (high_map - t) @ R
    predicted = range_image(local[np.linalg.norm(local, axis=1) < RANGE_M])
    where = np.isfinite(predicted)
    seen, expected = range_image(scan)[where], predicted[where]
    contradicted = np.count_nonzero(seen > expected + AGREE_M)
    confirmed = np.count_nonzero(np.abs(seen - expected) <= AGREE_M)
    return explained, contradicted / max(1, contradicted + confirmed)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("map_dataset", type=pathlib.Path)
    parser.add_argument("run_dataset", type=pathlib.Path)
    parser.add_argument("--scans", type=int, default=30)
    parser.add_argument("--min-z", type=float, default=1.0)
    parser.add_argument("--center", default="0,0", metavar="X,Y")
    args = parser.parse_args()
    center = np.array([float(v) for v in args.center.split(",")])

    _, map_poses = read_tum(args.map_dataset / "poses_gt.txt")
    world = voxelized(np.vstack([
        read_pcd(args.map_dataset / "scans" / f"{i:06d}.pcd") @ T[:3, :3].T + T[:3, 3]
        for i, T in list(enumerate(map_poses))[::5]
    ]), 0.1)
    world_tree = cKDTree(world)
    high_map = world[world[:, 2] >= args.min_z]
    times, run_poses = read_tum(args.run_dataset / "poses_gt.txt")
    turns = (0, 90, 180, 270)
    print(f"map: {len(world)} points, {len(high_map)} at least {args.min_z} m high")
    print("t (s) | explained: truth, turned " + " / ".join(map(str, turns[1:]))
          + " | contradicted: the same")
    for i in range(0, min(args.scans, len(run_poses)), 2):
        scan = read_pcd(args.run_dataset / "scans" / f"{i:06d}.pcd")
        scan = scan[np.linalg.norm(scan, axis=1) < RANGE_M]
        sent = voxelized(scan, SENT_VOXEL_M)
        figures = [evidence(scan, sent, turn_about(center, d) @ run_poses[i], world_tree, high_map,
                            args.min_z)
                   for d in turns]
        print(f"{times[i]:5.1f} | " + " ".join(f"{e:.3f}" for e, _ in figures)
              + " | " + " ".join(f"{c:.3f}" for _, c in figures))


if __name__ == "__main__":
    main()
