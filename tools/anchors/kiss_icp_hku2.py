#!/usr/bin/env python3
"""KISS-ICP odometry anchor on ../shared/data/hku2_avia (Livox Avia class, PCD x y z intensity):
KISS-ICP 1.3 Python API, no deskewing (the scans are motion-compensated), max range 100 m,
`python kiss_icp_hku2.py VOXEL` (0.5 as for balm_os0); prints the aligned ATE of every scan
against poses.txt, its maximum and the scans more than 0.3 m off. Install `kiss-icp numpy`
in a venv outside the repository (see kiss_icp_odometry.py).
"""
import sys, pathlib, numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from ate import ate, read_tum
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
D = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "hku2_avia"
def read_pcd(path):
    raw = path.read_bytes(); off = 0; h = {}
    while True:
        e = raw.index(b"\n", off); line = raw[off:e].decode().strip(); off = e + 1
        if line and not line.startswith("#"):
            k, *v = line.split(); h[k] = v
            if k == "DATA": break
    n = int(h["POINTS"][0]); f = len(h["FIELDS"])
    return np.frombuffer(raw, dtype="<f4", count=f * n, offset=off).reshape(n, f)[:, :3].astype(np.float64)
voxel = float(sys.argv[1])
c = KISSConfig(); c.data.deskew = False; c.data.max_range = 100.0; c.mapping.voxel_size = voxel; c.registration.max_num_threads = 1
odo = KissICP(c)
stamps, ref = read_tum(D / "poses.txt")
est = []
for p in sorted((D / "scans").glob("*.pcd")):
    odo.register_frame(read_pcd(p), np.array([])); est.append(odo.last_pose.copy())
est = np.array(est)
e, _ = ate(est[:, :3, 3], ref[:, :3, 3]); print(f"KISS-ICP voxel {voxel}: ATE RMS {np.sqrt(np.mean(e**2)):.4f} m, max {e.max():.3f} m, scans over 0.3 m {int((e>0.3).sum())}")
