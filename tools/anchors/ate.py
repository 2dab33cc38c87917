#!/usr/bin/env python3
"""Trajectory error yardstick shared by the anchors and kfmap (needs only numpy).

`python ate.py EST.tum REF.tum [--by-order] [--no-align] [--json]`

TUM files hold `t x y z qx qy qz qw` per line. Poses are matched by timestamp (nearest
reference pose within 1 ms) or, with --by-order, line by line. By default the estimate
positions are rigidly aligned onto the reference positions (Umeyama / Horn, rotation +
translation, no scale) and the absolute trajectory error (ATE) of the positions is
printed: RMS, max and median (m). With --no-align both trajectories are taken to be in
the same frame (localization) and translation (m) and rotation (deg) errors are printed.
--json prints one JSON object with the per-pose errors as well.
"""
import argparse
import json

import numpy as np


def quat_to_rot(q):
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rot_to_quat(R):
    """(qx, qy, qz, qw) of a rotation matrix, qw >= 0 (Shepperd's method)."""
    tr = np.trace(R)
    k = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], tr]))
    if k == 3:
        q = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1 + tr])
    else:
        i, j, l = k, (k + 1) % 3, (k + 2) % 3
        q = np.empty(4)
        q[i] = 1 + 2 * R[i, i] - tr
        q[j] = R[j, i] + R[i, j]
        q[l] = R[l, i] + R[i, l]
        q[3] = R[l, j] - R[j, l]
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def read_tum(path):
    """Timestamps (N,) and 4x4 poses (N, 4, 4) of a TUM file."""
    rows = np.loadtxt(path, ndmin=2)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for T, r in zip(poses, rows):
        T[:3, :3] = quat_to_rot(r[4:8])
        T[:3, 3] = r[1:4]
    return rows[:, 0], poses


def write_tum(path, times, poses):
    with open(path, "w") as f:
        for t, T in zip(times, poses):
            q = rot_to_quat(T[:3, :3])
            f.write(f"{t:.6f} {T[0, 3]:.6f} {T[1, 3]:.6f} {T[2, 3]:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def match(est_times, ref_times, by_order=False, tolerance=1e-3):
    """Index pairs (i_est, i_ref) of matched poses."""
    if by_order:
        n = min(len(est_times), len(ref_times))
        return np.arange(n), np.arange(n)
    pairs = [(i, int(np.argmin(np.abs(ref_times - t)))) for i, t in enumerate(est_times)]
    pairs = [(i, j) for i, j in pairs if abs(ref_times[j] - est_times[i]) <= tolerance]
    return np.array([p[0] for p in pairs], dtype=int), np.array([p[1] for p in pairs], dtype=int)


def align_rigid(est, ref):
    """R, t minimising sum |R est + t - ref|^2 (Umeyama without scale); est, ref are (N, 3)."""
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    U, _, Vt = np.linalg.svd((ref - mu_r).T @ (est - mu_e))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return R, mu_r - R @ mu_e


def ate(est_positions, ref_positions):
    """Per-pose position errors (m) after rigid alignment, and the alignment (R, t)."""
    R, t = align_rigid(est_positions, ref_positions)
    return np.linalg.norm(est_positions @ R.T + t - ref_positions, axis=1), (R, t)


def pose_errors(est_poses, ref_poses):
    """Per-pose translation (m) and rotation (deg) errors, no alignment (same frame)."""
    d = np.linalg.inv(ref_poses) @ est_poses
    cos = np.clip((np.trace(d[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.linalg.norm(est_poses[:, :3, 3] - ref_poses[:, :3, 3], axis=1), np.degrees(np.arccos(cos))


def summary(errors):
    return {"rms": float(np.sqrt(np.mean(errors**2))), "max": float(errors.max()), "median": float(np.median(errors))}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("est")
    parser.add_argument("ref")
    parser.add_argument("--by-order", action="store_true", help="match poses line by line, not by timestamp")
    parser.add_argument("--no-align", action="store_true", help="same frame: translation and rotation errors")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    est_t, est = read_tum(args.est)
    ref_t, ref = read_tum(args.ref)
    i, j = match(est_t, ref_t, args.by_order)
    if len(i) < 3:
        raise SystemExit(f"only {len(i)} poses matched")
    out = {"matched": len(i), "estimate_poses": len(est), "times": ref_t[j].tolist()}
    if args.no_align:
        trans, rot = pose_errors(est[i], ref[j])
        out.update(translation=summary(trans), rotation_deg=summary(rot),
                   translation_errors=trans.tolist(), rotation_errors_deg=rot.tolist())
        text = (f"{len(i)} poses, translation RMS {out['translation']['rms']:.3f} m, max {trans.max():.3f} m, "
                f"median {np.median(trans):.3f} m; rotation RMS {out['rotation_deg']['rms']:.2f} deg, max {rot.max():.2f} deg")
    else:
        err, _ = ate(est[i, :3, 3], ref[j, :3, 3])
        out.update(ate=summary(err), errors=err.tolist())
        text = f"{len(i)} poses, ATE RMS {out['ate']['rms']:.3f} m, max {err.max():.3f} m, median {np.median(err):.3f} m"
    print(json.dumps(out) if args.json else text)


if __name__ == "__main__":
    main()
