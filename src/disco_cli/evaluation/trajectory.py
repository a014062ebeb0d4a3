"""Trajectory errors, as evo reports them: ATE after a planar rigid alignment, and RPE.

A trajectory is `[N, 4, 4]` poses (T_world<-sensor, metres), estimate and truth one
pose per scan in the same order.

- `ate`: the estimate is first turned about z and shifted (x, y, z) onto the truth by
  least squares (a planar rigid alignment: no scale, no roll or pitch, as odometry of
  a ground vehicle keeps gravity), then the root mean square of the position errors.
- `rpe`: the error of each relative motion over `delta` scans, `inv(E_i) E_i+d` against
  `inv(G_i) G_i+d`: the root mean square of its translation (m) and of its angle (deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from disco_cli.errors import DiscoError

__all__ = ["TrajectoryErrors", "align_planar", "ate", "rpe", "trajectory_errors"]


def _pair(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    E = np.asarray(estimate, dtype=np.float64)
    G = np.asarray(truth, dtype=np.float64)
    if E.ndim != 3 or E.shape[1:] != (4, 4) or E.shape != G.shape:
        raise DiscoError(f"trajectories of {E.shape} and {G.shape} poses cannot be compared")
    if len(E) == 0:
        raise DiscoError("no poses to compare")
    return E, G


def align_planar(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The 4 x 4 turn about z and shift that best lays `estimate`'s positions onto
    `truth`'s (least squares; Umeyama's method in the plane, no scale)."""
    E, G = _pair(estimate, truth)
    p, q = E[:, :3, 3], G[:, :3, 3]
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    a, b = p[:, :2] - pc[:2], q[:, :2] - qc[:2]
    # The angle maximising sum(b . R(theta) a).
    theta = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    c, s = math.cos(theta), math.sin(theta)
    A = np.eye(4)
    A[:2, :2] = [[c, -s], [s, c]]
    A[:3, 3] = qc - A[:3, :3] @ pc
    return A


def ate(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Absolute trajectory error (m): RMS of the position errors after `align_planar`."""
    E, G = _pair(estimate, truth)
    A = align_planar(E, G)
    aligned = E[:, :3, 3] @ A[:3, :3].T + A[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - G[:, :3, 3]) ** 2, axis=1))))


def rpe(estimate: np.ndarray, truth: np.ndarray, delta: int = 1) -> tuple[float, float]:
    """Relative pose error over `delta` scans: (RMS translation m, RMS rotation deg);
    NaN for a trajectory of `delta` poses or fewer."""
    E, G = _pair(estimate, truth)
    if delta < 1:
        raise DiscoError(f"delta must be at least 1, not {delta}")
    if len(E) <= delta:
        return math.nan, math.nan
    rel_e = np.linalg.inv(E[:-delta]) @ E[delta:]
    rel_g = np.linalg.inv(G[:-delta]) @ G[delta:]
    err = np.linalg.inv(rel_g) @ rel_e
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    cos = np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    return float(np.sqrt(np.mean(trans**2))), float(np.sqrt(np.mean(rot**2)))


@dataclass(frozen=True)
class TrajectoryErrors:
    """ATE (m) and RPE over one scan (m, deg) of a trajectory against the truth."""

    ate_m: float
    rpe_m: float
    rpe_deg: float


def trajectory_errors(estimate: np.ndarray, truth: np.ndarray) -> TrajectoryErrors:
    """`ate` and `rpe` (delta 1) of `estimate` against `truth`."""
    t, r = rpe(estimate, truth)
    return TrajectoryErrors(ate(estimate, truth), t, r)
