"""Poses at given times: exact match, or interpolation between the two nearest poses.

`interpolate_poses(stamps, poses, times, max_gap)` is the one place where a scan (or a
bag message) gets its pose by time. Translation is interpolated linearly, rotation by
spherical linear interpolation (SLERP) of unit quaternions, which turns at a constant
rate about one axis from the earlier orientation to the later one: the rotation a
vehicle makes between two pose samples when its angular velocity is constant.

A time gets no pose (NaN) when it lies outside the pose file's span, or when either of
the two poses around it is more than `max_gap` seconds away: a far-away pose is never
handed out as if it were near.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from disco_cli.io.poses.geometry import matrix_to_quat, quat_to_matrix

__all__ = ["TimedPoses", "default_max_gap", "interpolate_poses", "slerp"]

# Times closer than this (seconds) are the same instant: a scan stamped with the pose's
# own stamp takes that pose as it is (no interpolation round-off).
EXACT_S = 1e-6
# The default largest gap, in median pose periods.
GAP_PERIODS = 3.0


@dataclass(frozen=True)
class TimedPoses:
    """Poses at times: `stamps` [M] seconds, increasing; `poses` [M, 4, 4] float64."""

    stamps: np.ndarray
    poses: np.ndarray


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions `[..., 4]` at fractions `s` [...].

    The shorter way round is taken (q and -q are one rotation); nearly equal quaternions
    fall back to normalized linear interpolation, where SLERP's division is ill-conditioned.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.array(q1, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_t = np.sin(theta)
    near = sin_t < 1e-9
    safe = np.where(near, 1.0, sin_t)
    w0 = np.where(near, 1.0 - s, np.sin((1.0 - s) * theta) / safe)
    w1 = np.where(near, s, np.sin(s * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def default_max_gap(stamps: np.ndarray) -> float:
    """`GAP_PERIODS` median sampling periods of the pose stamps (inf for a single pose)."""
    d = np.diff(np.asarray(stamps, dtype=np.float64))
    d = d[d > 0]
    return float(GAP_PERIODS * np.median(d)) if len(d) else float("inf")


def interpolate_poses(
    stamps: np.ndarray,
    poses: np.ndarray,
    times: np.ndarray,
    max_gap: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses `[N, 4, 4]` at `times` [N] (seconds) from poses at `stamps` [M] (seconds).

    - a time within `EXACT_S` of a stamp takes that pose unchanged;
    - otherwise the two stamps around it are interpolated (linear translation, SLERP
      rotation), when both lie within `max_gap` seconds of the time;
    - otherwise (outside the stamps' span, or in a gap wider than allowed) the pose is
      NaN.

    `max_gap` defaults to `default_max_gap(stamps)` (three median pose periods). Stamps
    need not be sorted; equal stamps keep the first pose. Returns `(poses, found)` with
    `found` [N] bool.
    """
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if poses.shape != (len(stamps), 4, 4):
        raise ValueError(f"poses must be [{len(stamps)}, 4, 4], got {poses.shape}")
    out = np.full((len(times), 4, 4), np.nan)
    found = np.zeros(len(times), dtype=bool)
    if len(stamps) == 0 or len(times) == 0:
        return out, found
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    keep = np.r_[True, np.diff(stamps) > 0]
    stamps, poses = stamps[keep], poses[keep]
    gap = default_max_gap(stamps) if max_gap is None else float(max_gap)

    # The nearest stamp at or after each time, and the one before it.
    hi = np.clip(np.searchsorted(stamps, times), 0, len(stamps) - 1)
    lo = np.clip(hi - 1, 0, len(stamps) - 1)
    exact_hi = np.abs(stamps[hi] - times) <= EXACT_S
    exact_lo = np.abs(stamps[lo] - times) <= EXACT_S
    exact = exact_hi | exact_lo
    which = np.where(exact_hi, hi, lo)
    out[exact] = poses[which[exact]]
    found[exact] = True

    between = ~exact & (stamps[lo] < times) & (times < stamps[hi])
    between &= (times - stamps[lo] <= gap) & (stamps[hi] - times <= gap)
    idx = np.flatnonzero(between)
    if len(idx):
        a, b = lo[idx], hi[idx]
        s = (times[idx] - stamps[a]) / (stamps[b] - stamps[a])
        q = slerp(matrix_to_quat(poses[a, :3, :3]), matrix_to_quat(poses[b, :3, :3]), s)
        T = np.tile(np.eye(4), (len(idx), 1, 1))
        T[:, :3, :3] = quat_to_matrix(q)
        T[:, :3, 3] = (1.0 - s)[:, None] * poses[a, :3, 3] + s[:, None] * poses[b, :3, 3]
        out[idx] = T
        found[idx] = True
    return out, found
