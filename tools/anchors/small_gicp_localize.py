#!/usr/bin/env python3
"""small_gicp localization anchor on ../shared/data/balm_os0 (install `small-gicp numpy`
in a venv outside the repository, as for kiss_icp_odometry.py).

Map: scans [0, --map-end) (default 116) moved into the world by poses.txt, merged,
downsampled to 0.25 m voxels and preprocessed once (covariances k = 10, KD-tree).
Then scans [--map-end, end) are localized in order with GICP scan-to-whole-map
(`small_gicp.align`, scans downsampled to 0.25 m, --max-dist correspondence distance):
the first from its reference pose, each next from the previous estimate, or with
--motion-model from the previous estimate times the last estimated motion (constant
velocity). Prints per-scan translation (m) and rotation (deg) errors against poses.txt
(same frame, no alignment), RMS / max, the number of scans over 0.5 m and over 0.25 m or
2 deg, and the per-scan latency (preprocessing + registration) p50 / p99.

`python small_gicp_localize.py [--motion-model] [--max-dist 1.0] [--threads 2] [--out est.tum]`
"""
import argparse
import pathlib
import time

import numpy as np
import small_gicp

from ate import pose_errors, write_tum  # same folder
from balm_pcd import DATA, poses, read_pcd, scan_paths


def build_map(paths, world_poses, threads):
    clouds = [read_pcd(p) @ T[:3, :3].T + T[:3, 3] for p, T in zip(paths, world_poses)]
    return small_gicp.preprocess_points(np.concatenate(clouds), 0.25, num_neighbors=10, num_threads=threads)


def main():
    parser = argparse.ArgumentParser(description="small_gicp scan-to-map localization anchor")
    parser.add_argument("--dataset", type=pathlib.Path, default=DATA)
    parser.add_argument("--map-end", type=int, default=116, help="map = scans [0, map-end)")
    parser.add_argument("--end", type=int, default=None, help="one past the last localized scan")
    parser.add_argument("--max-dist", type=float, default=1.0, help="max correspondence distance (m)")
    parser.add_argument("--motion-model", action="store_true", help="constant-velocity prediction")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="estimated poses, TUM")
    args = parser.parse_args()

    times, ref = poses(args.dataset)
    paths = scan_paths(args.dataset)
    t0 = time.perf_counter()
    target, tree = build_map(paths[: args.map_end], ref[: args.map_end], args.threads)
    print(f"map: scans 0..{args.map_end - 1}, {target.size()} points after 0.25 m voxels, "
          f"built in {time.perf_counter() - t0:.1f} s")

    used = list(range(args.map_end, args.end or len(paths)))
    est, ms = [], []
    pose, motion = ref[used[0]].copy(), np.eye(4)
    print(" scan  trans_m  rot_deg  ms  iters  inliers")
    for i in used:
        points = read_pcd(paths[i])
        t0 = time.perf_counter()
        source, _ = small_gicp.preprocess_points(points, 0.25, num_neighbors=10, num_threads=args.threads)
        guess = pose @ motion if args.motion_model else pose
        result = small_gicp.align(target, source, tree, guess, max_correspondence_distance=args.max_dist,
                                  num_threads=args.threads)
        ms.append((time.perf_counter() - t0) * 1e3)
        motion = np.linalg.inv(pose) @ result.T_target_source
        pose = result.T_target_source
        est.append(pose)
        trans, rot = pose_errors(pose[None], ref[i][None])
        print(f"{i:5d} {trans[0]:8.3f} {rot[0]:8.2f} {ms[-1]:4.0f} {result.iterations:6d} "
              f"{result.num_inliers / source.size():8.2f}")

    est = np.array(est)
    if args.out:
        write_tum(args.out, times[used], est)
    trans, rot = pose_errors(est, ref[used])
    bad = (trans > 0.25) | (rot > 2.0)
    print(f"{'constant velocity' if args.motion_model else 'previous pose'}, max-dist {args.max_dist} m, "
          f"{args.threads} threads, scans {used[0]}..{used[-1]} ({len(used)})")
    print(f"translation RMS {np.sqrt(np.mean(trans**2)):.3f} m, max {trans.max():.3f} m (scan {used[int(np.argmax(trans))]}); "
          f"rotation RMS {np.sqrt(np.mean(rot**2)):.2f} deg, max {rot.max():.2f} deg")
    print(f"over 0.5 m: {int((trans > 0.5).sum())}; over 0.25 m or 2 deg: {int(bad.sum())} "
          f"{[used[k] for k in np.flatnonzero(bad)]}")
    print(f"latency p50 {np.percentile(ms, 50):.0f} ms, p99 {np.percentile(ms, 99):.0f} ms")


if __name__ == "__main__":
    main()
