#!/usr/bin/env python3
"""Reader for ../shared/data/balm_os0 (binary PCD v0.7 scans with FIELDS x y z float32,
poses.txt in TUM format, line N = T_world_lidar of scan N) and the command line shared by
the odometry anchors (kiss_icp_odometry.py, small_gicp_odometry.py). Needs only numpy.

`python balm_pcd.py` prints the point count of every scan and the path length.
"""
import argparse
import pathlib
import time

import numpy as np

from ate import ate, read_tum, summary, write_tum  # same folder

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "balm_os0"


def read_pcd(path):
    """(N, 3) float64 points of a binary PCD file whose fields are float32 and begin with
    x y z (balm_os0's; the simulator's add view_x view_y view_z, which are dropped)."""
    raw = pathlib.Path(path).read_bytes()
    header = {}
    offset = 0
    while True:
        end = raw.index(b"\n", offset)
        line = raw[offset:end].decode("ascii").strip()
        offset = end + 1
        if line and not line.startswith("#"):
            key, *values = line.split()
            header[key] = values
            if key == "DATA":
                break
    fields = header["FIELDS"]
    if (fields[:3] != ["x", "y", "z"] or header["TYPE"] != ["F"] * len(fields)
            or header["SIZE"] != ["4"] * len(fields) or header["DATA"] != ["binary"]):
        raise ValueError(f"{path}: only binary PCD of float32 fields beginning x y z is supported")
    n = int(header["POINTS"][0])
    values = np.frombuffer(raw, dtype="<f4", count=len(fields) * n, offset=offset)
    return values.reshape(n, len(fields))[:, :3].astype(np.float64)


def scan_paths(dataset=DATA):
    return sorted((pathlib.Path(dataset) / "scans").glob("*.pcd"))


def poses(dataset=DATA):
    """Timestamps (N,) and T_world_lidar (N, 4, 4) from poses.txt."""
    return read_tum(pathlib.Path(dataset) / "poses.txt")


def run_odometry(name, make_estimator):
    """Parse --dataset/--start/--end/--step/--out/--threads, feed the scans to the estimator
    (`estimate(points) -> T_world_lidar`), write the TUM trajectory with the dataset's
    timestamps and print the aligned ATE against poses.txt for the scans used."""
    parser = argparse.ArgumentParser(description=f"{name} odometry over a balm_os0-style dataset")
    parser.add_argument("--dataset", type=pathlib.Path, default=DATA)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--end", type=int, default=None, help="one past the last scan (default: all)")
    parser.add_argument("--step", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="estimated trajectory, TUM")
    args = parser.parse_args()
    paths = scan_paths(args.dataset)
    times, ref = poses(args.dataset)
    used = list(range(len(paths)))[args.start:args.end:args.step]
    estimate = make_estimator(args.threads)
    est, seconds = [], []
    wall = time.perf_counter()
    for i in used:
        points = read_pcd(paths[i])
        t0 = time.perf_counter()
        est.append(estimate(points))
        seconds.append(time.perf_counter() - t0)
    wall = time.perf_counter() - wall
    est = np.array(est)
    if args.out:
        write_tum(args.out, times[used], est)
    err, _ = ate(est[:, :3, 3], ref[used, :3, 3])
    s = summary(err)
    ms = np.array(seconds) * 1e3
    print(f"{name}: scans {used[0]}..{used[-1]} step {args.step} ({len(used)} scans), {args.threads} threads")
    print(f"aligned ATE RMS {s['rms']:.3f} m, max {s['max']:.3f} m (scan {used[int(np.argmax(err))]}), median {s['median']:.3f} m")
    print(f"wall {wall:.1f} s incl. reading; per scan mean {ms.mean():.0f} ms, p50 {np.median(ms):.0f} ms, max {ms.max():.0f} ms (scan {used[int(np.argmax(ms))]})")
    return used, est, err


def main():
    times, ref = poses()
    counts = [len(read_pcd(p)) for p in scan_paths()]
    for i, c in enumerate(counts):
        print(f"{i:3d} {times[i]:.6f} {c}")
    steps = np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)
    print(f"{len(counts)} scans, {sum(counts)} points, path {steps.sum():.1f} m")


if __name__ == "__main__":
    main()
