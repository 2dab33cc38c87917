"""Test helpers: reading the simulated dataset and running the ``kfmap`` CLI as oracle."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np

PCD_TYPES = {("F", "4"): "<f4", ("F", "8"): "<f8", ("U", "1"): "u1", ("U", "2"): "<u2",
             ("U", "4"): "<u4", ("I", "1"): "i1", ("I", "2"): "<i2", ("I", "4"): "<i4"}


def read_pcd(path: Path) -> np.ndarray:
    """A binary PCD file as a structured array (fields by name)."""
    with open(path, "rb") as f:
        header: dict[str, list[str]] = {}
        while "DATA" not in header:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: no DATA line")
            words = line.decode("ascii").split()
            if words and not words[0].startswith("#"):
                header[words[0]] = words[1:]
        assert header["DATA"] == ["binary"], header["DATA"]
        dtype = np.dtype([
            (name, PCD_TYPES[(kind, size)], (int(count),) if int(count) > 1 else ())
            for name, size, kind, count in zip(
                header["FIELDS"], header["SIZE"], header["TYPE"], header["COUNT"])
        ])
        n = int(header["POINTS"][0])
        return np.frombuffer(f.read(n * dtype.itemsize), dtype=dtype, count=n)


def scan_points(dataset: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and view directions (float32, N x 3) of scan ``index``."""
    rec = read_pcd(dataset / "scans" / f"{index:06d}.pcd")
    points = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    views = np.stack([rec["view_x"], rec["view_y"], rec["view_z"]], axis=1)
    return points, views


def ground_truth(dataset: Path) -> np.ndarray:
    """``poses_gt.txt`` rows: t x y z qx qy qz qw."""
    return np.loadtxt(dataset / "poses_gt.txt", comments="#", ndmin=2)


def imu_samples(dataset: Path) -> np.ndarray:
    """``imu.csv`` rows: t ax ay az gx gy gz."""
    return np.loadtxt(dataset / "imu.csv", delimiter=",", skiprows=1, ndmin=2)


def yaw_deg(quat: np.ndarray) -> float:
    """Yaw of a quaternion (qx qy qz qw) of a level pose, degrees."""
    return math.degrees(2.0 * math.atan2(quat[2], quat[3]))


def euler_wire(x: float, y: float, z: float, roll_deg: float, pitch_deg: float,
               yaw: float) -> list[float]:
    """The wire pose (x y z qx qy qz qw) the kfmap CLI sends for ``--pose "x y z r p y"``:
    nalgebra's ``from_euler_angles`` step by step, so the floats are the same bits."""
    (sr, cr), (sp, cp), (sy, cy) = (
        (math.sin(math.radians(a) * 0.5), math.cos(math.radians(a) * 0.5))
        for a in (roll_deg, pitch_deg, yaw)
    )
    w = cr * cp * cy + sr * sp * sy
    q = [sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]
    if w < 0:
        w, q = -w, [-v for v in q]
    return [x, y, z, *q, w]


def write_xyz_bin(path: Path, points: np.ndarray) -> Path:
    """A raw x y z float32 ``.bin`` cloud with its ``.layout`` sidecar for the CLI."""
    np.ascontiguousarray(points, dtype="<f4").tofile(path)
    Path(f"{path}.layout").write_text("xyz\n")
    return path


def cli_query(server, points_file: Path, pose_text: str, kind: str, out: Path,
              *extra: str) -> dict[str, np.ndarray]:
    """Runs ``kfmap query`` and reads its CSV into arrays named as ``kfmap.Pairings``."""
    done = subprocess.run(
        [server.bin, "query", "--map-name", server.map_name, "--iceoryx-prefix",
         server.prefix, "--points", points_file, f"--pose={pose_text}", "--kind", kind,
         "--out", out, "--timeout", "60", *extra],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, f"kfmap query failed: {done.stderr}"
    rows = [line.split(",") for line in out.read_text().splitlines()[1:] if line]
    cols = list(zip(*rows)) if rows else [()] * 13
    floats = [np.array([float(v) for v in c], dtype=np.float64).astype(np.float32)
              for c in cols[3:]]
    return {
        "query": np.array(cols[0], dtype=np.uint32),
        "keyframe": np.array(cols[1], dtype=np.uint64),
        "local_index": np.array(cols[2], dtype=np.uint32),
        "point": np.stack(floats[0:3], axis=1) if rows else np.empty((0, 3), np.float32),
        "dist_sq": floats[3],
        "information": np.stack(floats[4:10], axis=1) if rows else np.empty((0, 6), np.float32),
    }


def transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points moved by a 4x4 pose (float64)."""
    p = np.asarray(points, dtype=np.float64)
    return p @ pose[:3, :3].T + pose[:3, 3]


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation between the rotation blocks of two poses, degrees."""
    r = a[:3, :3].T @ b[:3, :3]
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0))))
