#!/usr/bin/env python3
"""small_gicp as an independent oracle for map consistency on balm_os0 (the joint refinement's check; install
`small-gicp numpy scipy` in a venv outside the repository, as for kiss_icp_odometry.py).

Which trajectory agrees best with small_gicp's own registration of scan pairs: revisit
pairs (each scan 116-176 onto the nearest first-pass scan more than 20 scans away, within
5 m by the first trajectory) and same-pass pairs (scan i onto i-4). Each pair: GICP,
coarse 0.5 m then fine 0.1 m voxels, 20 neighbours, 1 m correspondences, from the first
trajectory's relative pose; kept with >= 30 % inliers. Per trajectory and pair set, the
RMS / median / max of |t| and the angle of T_traj_rel^-1 T_gicp.

Line N of every TUM file = T_world_lidar of scan N; frames may differ between files
(only relative poses are compared). Measured in docs/DESIGN.md#notes-refine:

  kfmap bake --dataset ../shared/data/balm_os0 --build-poses --out /tmp/b.kfmap --trajectory-out /tmp/built.tum
  kfmap bake --dataset ../shared/data/balm_os0 --poses ../shared/data/balm_os0/poses.txt \
      --refine-only --out /tmp/a.kfmap --trajectory-out /tmp/adjusted.tum
  python small_gicp_pairs.py --scans ../shared/data/balm_os0/scans \
      --traj A=../shared/data/balm_os0/poses.txt B=/tmp/built.tum C=/tmp/adjusted.tum \
      --init2 B --out /tmp/pairs.json
"""
import argparse
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np
import small_gicp
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

THREADS = 2
COARSE_RES, FINE_RES = 0.5, 0.1
NUM_NEIGHBORS = 20
MAX_CORR_COARSE, MAX_CORR_FINE = 1.0, 1.0
MAX_ITER = 64
REG = "GICP"
MIN_INLIER_SHARE = 0.30
OVERLAP_DIST = 0.2  # extra, independent overlap metric (NN distance after alignment)


def load_tum(path):
    rows = []
    for line in open(path):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        rows.append([float(x) for x in s.split()])
    a = np.array(rows)
    assert a.shape == (177, 8), (path, a.shape)
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()  # scipy: x y z w
    T[:, :3, 3] = a[:, 1:4]
    return T


def read_pcd_xyz(path):
    with open(path, "rb") as f:
        header = {}
        while True:
            line = f.readline().decode("ascii").strip()
            k, _, v = line.partition(" ")
            header[k] = v
            if k == "DATA":
                break
        assert header["FIELDS"] == "x y z" and header["DATA"] == "binary", header
        n = int(header["POINTS"])
        pts = np.frombuffer(f.read(12 * n), dtype="<f4").reshape(n, 3)
    return pts.astype(np.float64)


def inv(T):
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def err(T):
    ang = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(T[:3, 3])), float(ang)


class Scans:
    def __init__(self, d):
        self.d = d
        self.cache = {}

    def get(self, k):
        if k not in self.cache:
            raw = read_pcd_xyz(os.path.join(self.d, "%06d.pcd" % k))
            c, ct = small_gicp.preprocess_points(raw, COARSE_RES, NUM_NEIGHBORS, THREADS)
            f, ft = small_gicp.preprocess_points(raw, FINE_RES, NUM_NEIGHBORS, THREADS)
            self.cache[k] = dict(c=c, ct=ct, f=f, ft=ft, fnp=f.points()[:, :3].copy(),
                                 kd=None)
        return self.cache[k]


def register(scans, i, j, T_init, reverse=False):
    """Register scan i (source) onto scan j (target), coarse 0.5 m then fine 0.1 m GICP.
    reverse=True: register j onto i instead and return the inverse (same convention T_j<-i)."""
    if reverse:
        g = register(scans, j, i, inv(T_init))
        g["T"] = inv(np.array(g["T"])).tolist()
        return g
    S, Tg = scans.get(i), scans.get(j)
    r1 = small_gicp.align(Tg["c"], S["c"], Tg["ct"], init_T_target_source=T_init,
                          registration_type=REG, max_correspondence_distance=MAX_CORR_COARSE,
                          num_threads=THREADS, max_iterations=MAX_ITER)
    r2 = small_gicp.align(Tg["f"], S["f"], Tg["ft"], init_T_target_source=r1.T_target_source,
                          registration_type=REG, max_correspondence_distance=MAX_CORR_FINE,
                          num_threads=THREADS, max_iterations=MAX_ITER)
    T = np.array(r2.T_target_source)
    n_src = S["f"].size()
    # independent overlap: share of source points within OVERLAP_DIST of a target point
    if Tg["kd"] is None:
        Tg["kd"] = cKDTree(Tg["fnp"])
    src = S["fnp"] @ T[:3, :3].T + T[:3, 3]
    dist, _ = Tg["kd"].query(src, k=1, distance_upper_bound=OVERLAP_DIST, workers=THREADS)
    ok = np.isfinite(dist)
    return dict(T=T.tolist(), converged=bool(r1.converged and r2.converged),
                conv_coarse=bool(r1.converged), conv_fine=bool(r2.converged),
                iters=[int(r1.iterations), int(r2.iterations)],
                inlier_share=float(r2.num_inliers) / n_src,
                overlap02=float(ok.mean()),
                median_nn02=float(np.median(dist[ok])) if ok.any() else None,
                error=float(r2.error), n_src=int(n_src))


def make_pairs(TA):
    p = TA[:, :3, 3]
    revisit = []
    for i in range(116, 177):
        # candidates: j in 0..115 with |i-j| > 20, nearest by position in A, kept if <= 5 m
        cand = [j for j in range(0, 116) if abs(i - j) > 20]
        d = np.linalg.norm(p[cand] - p[i], axis=1)
        k = int(np.argmin(d))
        if d[k] <= 5.0:
            revisit.append((i, cand[k], float(d[k])))
    control = [(i, i - 4, float(np.linalg.norm(p[i] - p[i - 4]))) for i in range(4, 177, 4)]
    return revisit, control


def stats(ts, rs):
    ts, rs = np.asarray(ts), np.asarray(rs)
    return dict(n=int(len(ts)), rms_t=float(np.sqrt(np.mean(ts ** 2))), med_t=float(np.median(ts)),
                max_t=float(ts.max()), rms_r=float(np.sqrt(np.mean(rs ** 2))),
                med_r=float(np.median(rs)), max_r=float(rs.max()))


def main():
    global NUM_NEIGHBORS, MAX_CORR_FINE, REG
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", required=True)
    ap.add_argument("--traj", nargs="+", required=True, help="NAME=path.tum; first is the init/pairing one (A)")
    ap.add_argument("--init2", default="B", help="second initial-guess trajectory for repeatability")
    ap.add_argument("--out", required=True)
    ap.add_argument("--nn", type=int, default=NUM_NEIGHBORS, help="num_neighbors for covariances")
    ap.add_argument("--fine-corr", type=float, default=MAX_CORR_FINE, help="max corr. distance, fine pass")
    ap.add_argument("--reg", default="GICP", help="small_gicp registration_type (GICP, PLANE_ICP, ICP)")
    ap.add_argument("--reverse", action="store_true", help="register j onto i and invert (direction check)")
    ap.add_argument("--perturb", type=int, default=0,
                    help="per revisit pair, this many extra starts = A-init perturbed by N(0,0.15 m)/N(0,1.5 deg) per axis")
    a = ap.parse_args()
    NUM_NEIGHBORS, MAX_CORR_FINE, REG = a.nn, a.fine_corr, a.reg
    t0 = time.time()
    trajs = {}
    for s in a.traj:
        k, _, v = s.partition("=")
        trajs[k] = load_tum(v)
    names = list(trajs)
    TA = trajs[names[0]]
    revisit, control = make_pairs(TA)
    print("revisit pairs:", [(i, j, round(d, 2)) for i, j, d in revisit], flush=True)
    print("control pairs:", len(control), flush=True)
    scans = Scans(a.scans)
    rng = np.random.default_rng(37)

    def rel(T, i, j):
        return inv(T[j]) @ T[i]

    results = {"params": dict(small_gicp_version=__import__("importlib.metadata").metadata.version("small_gicp"),
                              threads=THREADS, coarse_res=COARSE_RES, fine_res=FINE_RES,
                              num_neighbors=NUM_NEIGHBORS, max_corr_coarse=MAX_CORR_COARSE,
                              max_corr_fine=MAX_CORR_FINE, max_iter=MAX_ITER,
                              min_inlier_share=MIN_INLIER_SHARE, overlap_dist=OVERLAP_DIST,
                              registration_type=REG, reverse=a.reverse, perturb=a.perturb,
                              trajectories={k: v for k, _, v in (s.partition("=") for s in a.traj)}),
               "sets": {}}
    for setname, pairs in (("revisit", revisit), ("control", control)):
        rows = []
        for i, j, d in pairs:
            g = register(scans, i, j, rel(TA, i, j), a.reverse)
            g.update(i=i, j=j, dist_A=d)
            Tg = np.array(g["T"])
            g["keep"] = bool(g["converged"] and g["inlier_share"] >= MIN_INLIER_SHARE)
            g["disc"] = {k: err(inv(rel(T, i, j)) @ Tg) for k, T in trajs.items()}
            if setname == "revisit":
                g2 = register(scans, i, j, rel(trajs[a.init2], i, j), a.reverse)
                pert = []
                for _ in range(a.perturb):
                    P = np.eye(4)
                    P[:3, :3] = Rotation.from_rotvec(np.radians(rng.normal(0, 1.5, 3))).as_matrix()
                    P[:3, 3] = rng.normal(0, 0.15, 3)
                    T0 = rel(TA, i, j) @ P
                    gp = register(scans, i, j, T0, a.reverse)
                    pert.append(dict(start=err(P), converged=gp["converged"],
                                     diff=err(inv(Tg) @ np.array(gp["T"]))))
                g["perturb"] = pert
                g["init2"] = dict(converged=g2["converged"], inlier_share=g2["inlier_share"],
                                  diff=err(inv(Tg) @ np.array(g2["T"])),
                                  init_diff=err(inv(rel(TA, i, j)) @ rel(trajs[a.init2], i, j)))
                g["traj_vs"] = {f"{x}-{y}": err(inv(rel(trajs[x], i, j)) @ rel(trajs[y], i, j))
                                for n1, x in enumerate(names) for y in names[n1 + 1:]}
            rows.append(g)
            print(setname, i, j, "conv", g["converged"], "inl %.2f ov %.2f" % (g["inlier_share"], g["overlap02"]),
                  " ".join("%s:%.3f/%.2f" % (k, *v) for k, v in g["disc"].items()),
                  ("rep %.4f" % g["init2"]["diff"][0]) if "init2" in g else "",
                  "%.0fs" % (time.time() - t0), flush=True)
        kept = [r for r in rows if r["keep"]]
        summ = {k: stats([r["disc"][k][0] for r in kept], [r["disc"][k][1] for r in kept]) for k in names}
        out = dict(pairs=rows, n_total=len(rows), n_kept=len(kept),
                   n_not_converged=sum(not r["converged"] for r in rows),
                   n_low_inlier=sum(r["inlier_share"] < MIN_INLIER_SHARE for r in rows), summary=summ)
        if setname == "revisit":
            keys = list(kept[0]["traj_vs"]) if kept else []
            out["traj_vs"] = {k: stats([r["traj_vs"][k][0] for r in kept], [r["traj_vs"][k][1] for r in kept])
                              for k in keys}
            both = [r for r in kept if r["init2"]["converged"]]
            out["repeat"] = dict(n=len(both),
                                 gicp=stats([r["init2"]["diff"][0] for r in both], [r["init2"]["diff"][1] for r in both]),
                                 init=stats([r["init2"]["init_diff"][0] for r in both],
                                            [r["init2"]["init_diff"][1] for r in both]))
            pp = [q for r in kept for q in r.get("perturb", [])]
            if pp:
                out["perturb"] = dict(n_starts=len(pp), n_converged=sum(q["converged"] for q in pp),
                                      start=stats([q["start"][0] for q in pp], [q["start"][1] for q in pp]),
                                      gicp=stats([q["diff"][0] for q in pp], [q["diff"][1] for q in pp]),
                                      n_off_1cm=sum(q["diff"][0] > 0.01 for q in pp))
        results["sets"][setname] = out
    results["elapsed_s"] = time.time() - t0
    with open(a.out, "w") as f:
        json.dump(results, f, indent=1)
    print("done in %.0f s" % results["elapsed_s"])


if __name__ == "__main__":
    sys.exit(main())
