"""Poses as they travel: 4x4 ``T_map_sensor`` matrices in Python, ``x y z qx qy qz qw``
on the wire (``pose_to_wire`` / ``pose_from_wire`` in ``protocol/src/lib.rs``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .errors import InvalidArgument

#: Largest deviation of a wire quaternion's norm from 1 the server accepts.
QUAT_NORM_TOLERANCE = 1e-3
#: Largest ``|R^T R - I|`` of a pose matrix's rotation block (as ``kfmap`` CLI poses).
ROTATION_TOLERANCE = 1e-4


def quat_to_matrix(q: npt.ArrayLike) -> np.ndarray:
    """The 3x3 rotation of a quaternion ``(qx, qy, qz, qw)`` (normalized first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: npt.ArrayLike) -> np.ndarray:
    """The unit quaternion ``(qx, qy, qz, qw)`` of a 3x3 rotation, ``qw >= 0``."""
    m = np.asarray(r, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    quat = np.array(q) / np.linalg.norm(q)
    return -quat if quat[3] < 0 else quat


def pose_to_wire(pose: npt.ArrayLike | None, what: str = "pose") -> list[float]:
    """``x y z qx qy qz qw`` of a pose: a 4x4 homogeneous matrix, or already 7 values
    (``x y z qx qy qz qw``). ``None`` is the identity. Raises ``InvalidArgument``."""
    if pose is None:
        return [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    try:
        a = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidArgument(f"{what}: not numeric ({e})") from None
    if not np.all(np.isfinite(a)):
        raise InvalidArgument(f"{what}: values must be finite")
    if a.shape == (7,):
        norm = float(np.linalg.norm(a[3:]))
        if abs(norm - 1.0) >= QUAT_NORM_TOLERANCE:
            raise InvalidArgument(f"{what}: quaternion norm {norm:.6f} is not 1")
        return [float(v) for v in a]
    if a.shape != (4, 4):
        raise InvalidArgument(
            f"{what}: expected a 4x4 matrix or x y z qx qy qz qw, got shape {a.shape}"
        )
    if not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise InvalidArgument(f"{what}: the last row of a pose matrix must be 0 0 0 1")
    r = a[:3, :3]
    if np.linalg.norm(r.T @ r - np.eye(3)) > ROTATION_TOLERANCE or np.linalg.det(r) < 0:
        raise InvalidArgument(f"{what}: the 3x3 block of the matrix is not a rotation")
    return [float(v) for v in (*a[:3, 3], *matrix_to_quat(r))]


def pose_from_wire(values: npt.ArrayLike) -> np.ndarray:
    """The 4x4 matrix of ``x y z qx qy qz qw``."""
    v = np.asarray(values, dtype=np.float64)
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(v[3:])
    t[:3, 3] = v[:3]
    return t


def wire_pose_is_valid(values: npt.ArrayLike) -> bool:
    """True when finite with a unit quaternion (as the server's ``pose_from_wire``)."""
    v = np.asarray(values, dtype=np.float64)
    return bool(
        np.all(np.isfinite(v)) and abs(np.linalg.norm(v[3:]) - 1.0) < QUAT_NORM_TOLERANCE
    )


def roll_pitch_quat(roll: float, pitch: float) -> np.ndarray:
    """``(qx, qy, qz, qw)`` of ``Ry(pitch) Rx(roll)`` (nalgebra's ``from_euler_angles``
    with yaw 0): the rotation of a gravity correction."""
    sr, cr = np.sin(roll * 0.5), np.cos(roll * 0.5)
    sp, cp = np.sin(pitch * 0.5), np.cos(pitch * 0.5)
    return np.array([sr * cp, cr * sp, -sr * sp, cr * cp])
