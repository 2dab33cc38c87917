#!/usr/bin/env python3
"""KITTI-style drift of a trajectory against a reference (needs only numpy).

`python kitti_drift.py EST.tum REF.tum [--step K] [--json]`

The KITTI odometry benchmark's measure (its devkit, evaluate_odometry): from every K-th
reference pose a (default 1; the devkit uses 10), for each segment length L of 50, 100, ...,
400 m, the first pose b at least L further along the reference path; the relative error
inv(inv(G_a) G_b) inv(E_a) E_b of the estimate E against the reference G, its translation
over L (%) and its rotation angle over L (deg/100 m); both averaged over every segment of
every length. Poses are matched by timestamp (ate.py). The aligned ATE (ate.py) is printed
beside it, so one command gives the issue's three figures.
"""
import argparse
import json

import numpy as np

from ate import ate, match, read_tum, summary

LENGTHS_M = tuple(range(50, 401, 50))


def path_distances(poses):
    """Distance travelled along `poses` (N, 4, 4) up to each pose, metres."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def segment_errors(est, ref, lengths=LENGTHS_M, step=1):
    """(first, last, length, translation error / length, rotation error rad / length) of
    every segment."""
    along = path_distances(ref)
    out = []
    for a in range(0, len(ref), step):
        for length in lengths:
            beyond = np.nonzero(along >= along[a] + length)[0]
            if len(beyond) == 0:
                continue
            b = int(beyond[0])
            truth = np.linalg.inv(ref[a]) @ ref[b]
            moved = np.linalg.inv(est[a]) @ est[b]
            error = np.linalg.inv(moved) @ truth
            out.append((a, b, length, np.linalg.norm(error[:3, 3]) / length,
                        rotation_angle(error[:3, :3]) / length))
    return out


def drift(segments):
    """Mean translation drift (%) and rotation drift (deg/100 m) over `segments`."""
    if not segments:
        raise SystemExit("no segment fits: the reference path is shorter than 50 m")
    errors = np.array([s[3:] for s in segments])
    return 100.0 * errors[:, 0].mean(), np.degrees(errors[:, 1].mean()) * 100.0


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("est")
    parser.add_argument("ref")
    parser.add_argument("--step", type=int, default=1, help="start a segment at every K-th pose")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    est_times, est = read_tum(args.est)
    ref_times, ref = read_tum(args.ref)
    i, j = match(est_times, ref_times)
    if len(i) < 2:
        raise SystemExit(f"{args.est}: fewer than two poses match {args.ref} by time")
    est, ref = est[i], ref[j]
    errors, _ = ate(est[:, :3, 3], ref[:, :3, 3])
    segments = segment_errors(est, ref, step=args.step)
    translation, rotation = drift(segments)
    report = {
        "poses": int(len(i)),
        "path_m": float(path_distances(ref)[-1]),
        "ate_m": summary(errors),
        "drift_translation_percent": translation,
        "drift_rotation_deg_per_100m": rotation,
        "segments": len(segments),
    }
    if args.json:
        print(json.dumps(report))
        return
    print(f"{args.est}: {report['poses']} poses, reference path {report['path_m']:.1f} m")
    print(f"  aligned ATE RMS {report['ate_m']['rms']:.3f} m, max {report['ate_m']['max']:.3f} m")
    print(f"  drift (50-400 m, {len(segments)} segments): {translation:.2f} %, {rotation:.3f} deg/100 m")


if __name__ == "__main__":
    main()
