#!/usr/bin/env python3
"""Mean NEES of `kfmap localize --json-lines` poses against a reference, and how far
the scans' errors are correlated in time.

    tools/nees_time_correlation.py RUN.lines REFERENCE.tum [LABEL] [--map-from-input X,Y,Z,QX,QY,QZ,QW] [--quarters] [--axes] [--relative-motion]

RUN.lines is `kfmap localize --json-lines` output (one object per scan, in order, plus
a summary without "index"), REFERENCE.tum one TUM pose per scan in the frame of the
dataset the map was baked from (a simulated dataset's poses_gt.txt), moved into the
map frame by --map-from-input: the map's `T_map_input` as `kfmap status --json` or
`kfmap inspect --json` print it (bake's gravity levelling; identity when not given).
Only `ok` scans count.

Per group (rotation, position) it prints: the mean NEES (3 for a calibrated 3-dof
covariance), the effective number of independent scans N_eff = N / (1 + 2 sum_k
rho_k^2) from the lag-k correlation rho_k of the whitened error components (for
Gaussian errors, Var(mean NEES) = 6/N (1 + 2 sum rho_k^2)), the chi-square 95 %
band of a calibrated covariance's mean NEES for N independent scans and for N_eff,
and the chance that a calibrated covariance lands inside the independent-scan band.
--axes adds each sensor axis's error RMS and published sigma median (rotation in mdeg,
position in mm); --relative-motion what an online calibration from consecutive scans'
relative motion would see at best (the reference's exact relative motion standing in
for scan-to-scan registration): per group k = mean(d^T S^-1 d) / 3 over consecutive ok
pairs, d the relative-motion error, S = C_(i+1) + Ad C_i Ad^T with Ad the adjoint of
the inverse of the reported relative motion, and the mean NEES / k.
Needs numpy only (Wilson-Hilferty for the chi-square quantiles); TUM files and
quaternions are read by tools/anchors/ate.py.
"""
import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent / "anchors"))
from ate import quat_to_rot, read_tum  # noqa: E402  (the anchors' TUM reader and quaternions)


def normal_quantile(p):
    lo, hi = -10.0, 10.0
    for _ in range(100):
        mid = (lo + hi) / 2
        if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


def chi2_quantile(p, k):
    a = 2 / (9 * k)
    return k * (1 - a + normal_quantile(p) * math.sqrt(a)) ** 3


def chi2_cdf(x, k):
    a = 2 / (9 * k)
    z = ((x / k) ** (1 / 3) - (1 - a)) / math.sqrt(a)
    return 0.5 * (1 + math.erf(z / math.sqrt(2)))


def pose(xyz_quat):
    """The 4x4 matrix of ``[x, y, z, qx, qy, qz, qw]`` (a `--json-lines` pose)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rot(np.asarray(xyz_quat[3:7], dtype=float))
    T[:3, 3] = xyz_quat[:3]
    return T


def rotation_vector(M):
    angle = math.acos(max(-1.0, min(1.0, (np.trace(M) - 1) / 2)))
    axis = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return axis * (0.5 if angle < 1e-9 else angle / (2 * math.sin(angle)))


def ok_errors(scans, reference):
    """Per ok scan: (scan, d), d the right perturbation from the reported pose to the
    reference (4x4, sensor frame), as kfmap defines the covariance."""
    return [(scan, np.linalg.inv(pose(scan["pose"])) @ truth)
            for scan, truth in zip(scans, reference) if scan["status"] == "ok"]


def whitened_errors(scans, reference):
    """Per ok scan: (rotation, position) errors whitened by the published covariance's
    blocks; |w|^2 is the scan's NEES."""
    rows = []
    for scan, d in ok_errors(scans, reference):
        covariance = np.array(scan["covariance"]).reshape(6, 6)
        row = []
        for error, block in ((rotation_vector(d[:3, :3]), covariance[:3, :3]),
                             (d[:3, 3], covariance[3:, 3:])):
            root = np.linalg.cholesky(np.linalg.inv(block))
            row.append(root.T @ error)
        rows.append(row)
    return rows


def twist(T):
    """The (rotation vector, translation) of a 4x4 pose, as the covariance orders them."""
    return np.concatenate([rotation_vector(T[:3, :3]), T[:3, 3]])


def covariance_of(scan):
    return np.array(scan["covariance"]).reshape(6, 6)


def per_axis(ok):
    """Over `ok` ((scan, d) pairs of `ok_errors`): the error's RMS and the published
    sigma's median per sensor axis, rotation (roll, pitch, yaw) in mdeg and position
    (x forward, y left, z up) in mm."""
    to_display = np.array([1e3 * 180 / math.pi] * 3 + [1e3] * 3)
    errors = np.array([twist(d) for _, d in ok]) * to_display
    sigmas = np.array([np.sqrt(np.diag(covariance_of(s))) for s, _ in ok]) * to_display
    rms = np.sqrt((errors ** 2).mean(axis=0))
    median = np.median(sigmas, axis=0)
    rounded = lambda v: [round(float(x), 2) for x in v]
    return {"rotation_rms_mdeg": rounded(rms[:3]), "rotation_sigma_median_mdeg": rounded(median[:3]),
            "position_rms_mm": rounded(rms[3:]), "position_sigma_median_mm": rounded(median[3:])}


def position_by_quarter(scans, reference):
    """The ok scans in four consecutive quarters: per quarter the position error's RMS
    and the published sigma's median along each sensor axis (x forward, y left, z up),
    in mm, to see where along a drive the covariance under- or over-covers."""
    ok = ok_errors(scans, reference)
    quarters = []
    for q in range(4):
        part = ok[q * len(ok) // 4:(q + 1) * len(ok) // 4]
        axes = per_axis(part)
        quarters.append({
            "scans": [part[0][0]["index"], part[-1][0]["index"]],
            "error_rms_mm": axes["position_rms_mm"],
            "sigma_median_mm": axes["position_sigma_median_mm"],
        })
    return quarters


def adjoint(T):
    """The adjoint of T acting on (rotation, position) right perturbations."""
    R, t = T[:3, :3], T[:3, 3]
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew @ R
    return A


def relative_motion_k(scans, reference):
    """Per group, k = mean(d^T S^-1 d) / 3 over consecutive ok scans: d the error of the
    reported relative motion against the reference's, S = C_(i+1) + Ad C_i Ad^T with Ad
    the adjoint of the inverse of the reported relative motion."""
    pairs = ([], [])
    for i in range(1, len(scans)):
        if scans[i - 1]["status"] != "ok" or scans[i]["status"] != "ok":
            continue
        moved = np.linalg.inv(pose(scans[i - 1]["pose"])) @ pose(scans[i]["pose"])
        d = twist(np.linalg.inv(moved) @ np.linalg.inv(reference[i - 1]) @ reference[i])
        A = adjoint(np.linalg.inv(moved))
        S = covariance_of(scans[i]) + A @ covariance_of(scans[i - 1]) @ A.T
        for g in range(2):
            block = slice(3 * g, 3 * g + 3)
            pairs[g].append(d[block] @ np.linalg.solve(S[block, block], d[block]))
    return [float(np.mean(p)) / 3 for p in pairs]


def group_figures(w):
    n = len(w)
    nees = (w ** 2).sum(axis=1)
    mean = nees.mean()
    # Components scaled to unit variance, so rho_k is a correlation whatever the scale.
    x = w / math.sqrt(max(mean / 3, 1e-300))
    spread = 0.0
    for k in range(1, n // 4):
        rho = float(np.mean([np.mean(x[:-k, c] * x[k:, c]) for c in range(3)]))
        if rho <= 0.05:
            break
        spread += (1 - k / n) * rho ** 2
    n_eff = n / (1 + 2 * spread)
    band = lambda m: (chi2_quantile(0.025, 3 * m) / m, chi2_quantile(0.975, 3 * m) / m)
    independent, effective = band(n), band(n_eff)
    inside = chi2_cdf(independent[1] * n_eff, 3 * n_eff) - chi2_cdf(independent[0] * n_eff, 3 * n_eff)
    return {
        "mean_nees": round(mean, 2),
        "n_eff": round(n_eff, 1),
        "band_independent": [round(b, 2) for b in independent],
        "band_n_eff": [round(b, 2) for b in effective],
        "calibrated_inside_independent_band": round(inside, 2),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("lines", help="kfmap localize --json-lines output")
    parser.add_argument("reference", help="TUM poses, one per scan, in the dataset's frame")
    parser.add_argument("label", nargs="?", help="printed with the figures (default: LINES)")
    parser.add_argument("--map-from-input", metavar="X,Y,Z,QX,QY,QZ,QW",
                        help="the map's T_map_input (kfmap status --json or kfmap inspect --json)")
    parser.add_argument("--quarters", action="store_true",
                        help="also the position error and published sigma per sensor axis, by quarter of the run")
    parser.add_argument("--axes", action="store_true",
                        help="also the error RMS and published sigma per sensor axis")
    parser.add_argument("--relative-motion", action="store_true",
                        help="also what a calibration from consecutive scans' relative motion would see")
    args = parser.parse_args()
    map_from_input = np.eye(4)
    if args.map_from_input is not None:
        try:
            values = [float(v) for v in args.map_from_input.split(",")]
        except ValueError:
            values = []
        if len(values) != 7:
            parser.error("--map-from-input: expected X,Y,Z,QX,QY,QZ,QW")
        map_from_input = pose(values)
    scans = [json.loads(line) for line in open(args.lines) if line.strip()]
    scans = [s for s in scans if "index" in s]
    reference = [map_from_input @ p for p in read_tum(args.reference)[1]]
    if len(scans) != len(reference):
        sys.exit(f"{len(scans)} scans but {len(reference)} reference poses: one per scan expected")
    rows = whitened_errors(scans, reference)
    if len(rows) < 8:
        sys.exit(f"{len(rows)} ok scans: too few for a mean NEES")
    figures = {"label": args.label or args.lines, "ok": len(rows), "scans": len(scans)}
    groups = {name: np.array([r[g] for r in rows]) for g, name in ((0, "rotation"), (1, "position"))}
    for name, w in groups.items():
        figures[name] = group_figures(w)
    if args.quarters:
        figures["quarters"] = position_by_quarter(scans, reference)
    if args.axes:
        figures["axes"] = per_axis(ok_errors(scans, reference))
    if args.relative_motion:
        figures["relative_motion"] = {
            name: {"k": round(k, 2), "nees_over_k": round((groups[name] ** 2).sum(axis=1).mean() / k, 2)}
            for name, k in zip(("rotation", "position"), relative_motion_k(scans, reference))}
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
