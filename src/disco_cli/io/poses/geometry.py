"""Rigid-transform helpers: x, y, yaw; angle wrapping; rotations from Euler angles and
quaternions and back; inverses. Poses are 4 x 4 `T_world<-sensor` matrices.

Yaw convention (docs/architecture.md): the relative yaw of a query to a match is the
yaw of `T_match^-1 @ T_query`, i.e. the heading of the query sensor in the match's
frame, wrapped to (-180, 180] degrees.
"""

from __future__ import annotations

import numpy as np


def xy_yaw(T: np.ndarray) -> tuple:
    """(x, y, yaw in radians) of one 4 x 4 pose (floats) or of a stack (arrays)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"expected [..., 4, 4] poses, got {T.shape}")
    x, y = T[..., 0, 3], T[..., 1, 3]
    yaw = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    if T.ndim == 2:
        return float(x), float(y), float(yaw)
    return x, y, yaw


def pose_rows(T: np.ndarray) -> np.ndarray:
    """`[N, 4, 4]` poses as `[N, 4]` rows of x, y, z, yaw (radians)."""
    x, y, yaw = xy_yaw(np.asarray(T))
    return np.stack([x, y, np.asarray(T)[:, 2, 3], yaw], axis=1)


def wrap_deg(angle: np.ndarray | float) -> np.ndarray | float:
    """Angles in degrees wrapped to (-180, 180]."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = a - 360.0 * np.ceil((a - 180.0) / 360.0)
    return float(wrapped) if wrapped.ndim == 0 else wrapped


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (stack-aware), exact for rotations."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


_inv = inverse  # the name the revisit helpers used


def relative_yaw_deg(T_match: np.ndarray, T_query: np.ndarray) -> np.ndarray | float:
    """Yaw of `T_match^-1 @ T_query` in degrees, wrapped to (-180, 180] (broadcasts)."""
    T_match = np.asarray(T_match, dtype=np.float64)
    T_query = np.asarray(T_query, dtype=np.float64)
    rel = inverse(T_match) @ T_query
    return wrap_deg(np.degrees(np.arctan2(rel[..., 1, 0], rel[..., 0, 0])))


def rpy_to_matrix(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotations `Rz(yaw) @ Ry(pitch) @ Rx(roll)` (radians; arrays give `[N, 3, 3]`).

    This is the fixed-axis x-y-z (roll about x first) convention of NCLT's and MulRan's
    published poses and extrinsics.
    """
    r, p, y = (np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty(np.broadcast(r, p, y).shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def xyzrpy_to_4x4(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """4 x 4 poses from positions and `rpy_to_matrix` angles (radians)."""
    R = rpy_to_matrix(roll, pitch, yaw)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., 0, 3], T[..., 1, 3], T[..., 2, 3] = x, y, z
    T[..., 3, 3] = 1.0
    return T


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions `[..., 4]` as (x, y, z, w) -> rotations `[..., 3, 3]`.

    The quaternion is normalized first, so slightly off-unit inputs (text files) are fine.
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotations `[..., 3, 3]` -> unit quaternions `[..., 4]` (x, y, z, w), w >= 0.

    Each quaternion is taken from the largest of the four diagonal combinations, which
    keeps the square root away from zero (accurate for every rotation).
    """
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for k, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        cands = [tr, m[0, 0], m[1, 1], m[2, 2]]
        i = int(np.argmax(cands))
        if i == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        elif i == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif i == 2:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[k] = -q if q[3] < 0 else q
    return out.reshape(R.shape[:-2] + (4,))


def keep_by_spacing(xy: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of positions at least `spacing` metres of travel apart (all when <= 0)."""
    if spacing <= 0 or len(xy) == 0:
        return np.arange(len(xy))
    keep = [0]
    for i in range(1, len(xy)):
        if np.linalg.norm(xy[i] - xy[keep[-1]]) >= spacing:
            keep.append(i)
    return np.asarray(keep)
