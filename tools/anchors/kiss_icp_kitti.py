#!/usr/bin/env python3
"""KISS-ICP odometry anchor on raw KITTI scans (../shared/data/kitti00 by default: velodyne
.bin files, float32 x y z intensity, poses_velo_kitti.txt in the LiDAR frame, times.txt).
Install `kiss-icp numpy` in a venv outside the repository (see kiss_icp_odometry.py).

KISS-ICP 1.3's Python API (`kiss_icp.kiss_icp.KissICP`), max range 100 m, voxel 1.0 m
(its default for that range, max-range / 100), otherwise its defaults. Scans are read as its
KITTI loader reads them: x y z of the .bin, then `_correct_kitti_scan` (the 0.205 deg
vertical-angle correction KISS-ICP applies to every KITTI scan; --no-kitti-correction drops it).

--deskew chooses the motion compensation (KITTI's .bin has no per-point times):
  off    none. This is what KISS-ICP 1.3's own KITTI loader does: it returns no timestamps,
         and its preprocessor deskews only scans that have them.
  kiss   per-point times from the azimuth, as KISS-ICP 0.x derived them for KITTI
         (t = 0.5 (-atan2(y, x) / pi + 1): the sweep starts and ends behind the sensor,
         forward is mid-sweep), given to KISS-ICP's preprocessor, which normalises them to
         [0, 1] and spreads the last frame-to-frame motion over them: the sweep is taken to
         last one frame interval (right when every frame is used, twice the real motion
         with every second frame).
  sweep  the same azimuth times, but the last motion is scaled to one sweep
         (--sweep-seconds, 0.1 s for the HDL-64E at 10 Hz) before deskewing, so subsets
         with a step are compensated for the real sweep.
  mid    as sweep, but deskewed here (numpy) into the sensor frame at mid-sweep, where the
         ground truth is, instead of KISS-ICP's end of the sweep; KISS-ICP then gets the
         deskewed scan without times.
KISS-ICP deskews into the sensor frame at the end of the sweep (behind the sensor); the
ground truth is mid-sweep (the camera trigger, sensor facing forward). The first two frames
are not deskewed (no motion known yet), so from the third frame on its poses refer to a
time half a sweep later than those before: on a short run that jump (about 0.4 m at
8 m/s) lengthens the trajectory by itself; `mid` has no such jump.

Prints the aligned ATE (tools/anchors/ate.py) against the reference for the frames used and
writes the estimate as TUM (--out) with times.txt's stamps.

A dataset with a TUM poses_gt.txt or poses.txt instead (kfmap simulate --raw scans written as
.bin) is read too: pass --spin ccw --sweep-seconds 1/rate --no-kitti-correction; `mid` then
deskews into the frame at the sweep's start, where the simulator's poses are.

`python kiss_icp_kitti.py [--dataset D] [--start S] [--end E] [--step K] [--deskew off|kiss|sweep|mid]
 [--spin cw|ccw] [--sweep-seconds S] [--voxel V] [--no-kitti-correction] [--out est.tum]`
"""
import argparse
import pathlib

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from kiss_icp.pybind import kiss_icp_pybind

from ate import ate, read_tum, summary, write_tum  # same folder

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "kitti00"


def read_bin(path, correct):
    points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    if correct:
        points = np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(points)))
    return points


def azimuth_times(points, spin="cw"):
    """Share of the sweep (0 to 1) at each point. cw: KISS-ICP 0.x's KITTI times, 0 and 1
    behind the sensor, 0.5 forward; ccw: kfmap's simulator, counter-clockwise from +X."""
    az = np.arctan2(points[:, 1], points[:, 0])
    if spin == "ccw":
        return np.mod(az, 2 * np.pi) / (2 * np.pi)
    return 0.5 * (-az / np.pi + 1.0)


def hat(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def se3_log(T):
    """(rho, phi) with T = exp([rho, phi]) (SE(3) log, phi the rotation vector)."""
    R, t = T[:3, :3], T[:3, 3]
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    if angle < 1e-9:
        return t.copy(), np.zeros(3)
    phi = angle / (2 * np.sin(angle)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    W = hat(phi)
    V_inv = np.eye(3) - 0.5 * W + (1 / angle**2) * (1 - angle * np.sin(angle) / (2 * (1 - np.cos(angle)))) * W @ W
    return V_inv @ t, phi


def se3_exp(rho, phi):
    angle = np.linalg.norm(phi)
    W = hat(phi)
    if angle < 1e-9:
        R, V = np.eye(3) + W, np.eye(3)
    else:
        R = np.eye(3) + np.sin(angle) / angle * W + (1 - np.cos(angle)) / angle**2 * W @ W
        V = np.eye(3) + (1 - np.cos(angle)) / angle**2 * W + (angle - np.sin(angle)) / angle**3 * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ rho
    return T


def scale_motion(T, s):
    rho, phi = se3_log(T)
    return se3_exp(s * rho, s * phi)


def deskew_mid(points, times01, delta, sweep_share, stamp_share=0.5):
    """Points moved into the sensor frame at the stamp (sweep share stamp_share, mid-sweep
    for KITTI): a point at share u was seen (u - stamp_share) sweeps from there, the sensor
    then at exp(s log(delta)), s = (u - stamp_share) sweep_share."""
    rho, phi = se3_log(delta)
    s = (times01 - stamp_share) * sweep_share
    angle = np.linalg.norm(phi)
    axis = phi / angle if angle > 1e-12 else np.zeros(3)
    a = s * angle
    p = points
    cross = np.cross(axis, p)
    dot = p @ axis
    rotated = p * np.cos(a)[:, None] + cross * np.sin(a)[:, None] + np.outer(dot, axis) * (1 - np.cos(a))[:, None]
    out = rotated + np.outer(s, rho)  # V ~ I for the tiny rotation over a sweep
    return out


def read_reference(dataset):
    """Times (N,) and T_world_velo (N, 4, 4) of the dataset's poses_velo_kitti.txt / times.txt,
    or of its TUM poses_gt.txt (kfmap simulate) / poses.txt."""
    for name in ("poses_gt.txt", "poses.txt"):
        if (pathlib.Path(dataset) / name).exists():
            return read_tum(pathlib.Path(dataset) / name)
    rows = np.loadtxt(pathlib.Path(dataset) / "poses_velo_kitti.txt", ndmin=2)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return np.loadtxt(pathlib.Path(dataset) / "times.txt", ndmin=1), poses


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=pathlib.Path, default=DATA)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--end", type=int, default=None, help="one past the last frame (default: all)")
    parser.add_argument("--step", type=int, default=1)
    parser.add_argument("--deskew", choices=["off", "kiss", "sweep", "mid"], default="off")
    parser.add_argument("--sweep-seconds", type=float, default=0.1)
    parser.add_argument("--spin", choices=["cw", "ccw"], default="cw",
                        help="cw: KITTI (from behind, stamp forward); ccw: kfmap simulate --raw (from +X, stamp at start)")
    parser.add_argument("--voxel", type=float, default=1.0)
    parser.add_argument("--no-kitti-correction", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=pathlib.Path, default=None)
    args = parser.parse_args()
    times, ref = read_reference(args.dataset)
    paths = sorted(args.dataset.glob("*.bin"))
    used = list(range(len(paths)))[args.start:args.end:args.step]
    config = KISSConfig()
    config.data.deskew = args.deskew in ("kiss", "sweep")
    config.data.max_range = 100.0
    config.mapping.voxel_size = args.voxel
    config.registration.max_num_threads = args.threads
    odometry = KissICP(config)
    est, last_t = [], None
    for i in used:
        points = read_bin(paths[i], not args.no_kitti_correction)
        if args.deskew == "kiss":
            odometry.register_frame(points, azimuth_times(points, args.spin))
        elif args.deskew == "sweep":
            dt = times[i] - last_t if last_t is not None else args.sweep_seconds
            delta = scale_motion(odometry.last_delta, args.sweep_seconds / dt)
            deskewed = odometry.preprocessor.preprocess(points, azimuth_times(points, args.spin), delta)
            odometry.register_frame(deskewed, np.array([]))
        elif args.deskew == "mid":
            dt = times[i] - last_t if last_t is not None else args.sweep_seconds
            stamp_share = 0.0 if args.spin == "ccw" else 0.5
            deskewed = deskew_mid(points, azimuth_times(points, args.spin), odometry.last_delta,
                                  args.sweep_seconds / dt, stamp_share)
            odometry.register_frame(deskewed, np.array([]))
        else:
            odometry.register_frame(points, np.array([]))
        est.append(odometry.last_pose.copy())
        last_t = times[i]
    est = np.array(est)
    if args.out:
        write_tum(args.out, times[used], est)
    err, _ = ate(est[:, :3, 3], ref[used, :3, 3])
    s = summary(err)
    ref_step = np.linalg.norm(np.diff(ref[used, :3, 3], axis=0), axis=1).sum()
    est_step = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1).sum()
    correction = "off" if args.no_kitti_correction else "on"
    print(f"KISS-ICP: frames {used} deskew {args.deskew}, kitti correction {correction}, voxel {args.voxel}")
    print(f"aligned ATE RMS {s['rms']:.4f} m, max {s['max']:.4f} m, median {s['median']:.4f} m; "
          f"path {est_step:.3f} of {ref_step:.3f} m ({100 * est_step / ref_step:.1f} %)")


if __name__ == "__main__":
    main()
