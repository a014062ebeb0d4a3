"""The odometry's heading drift, estimated from the loops and taken out before the graph.

An odometry's heading error is rarely white: a gyro's bias, a tyre a little smaller
than the other or a LiDAR odometry that under-turns each corner add yaw at a steady
rate as the robot drives. A pose graph whose odometry edges are independent can only
bend the trajectory where loops pin it; between and beyond them the drift stays. When
the loops cluster on one stretch of a revisit, the rest of it keeps metres of error
that the same graph with every true loop would not (a quarter of the loops found, at
the start of the revisit, left the NCLT-like selection worlds at 2.9-3.9x the true
loops' ATE, against 1.16-1.21x with the drift fitted; docs/correct.md).

So the graph first fits one number, the yaw added per metre driven, to the loops: the
odometry is chained again with each step turned back by that rate, and the rate that
best closes the loops (each loop's whitened error under a robust loss, a Gaussian
prior of `PRIOR_DEG_PER_M` on the rate) is kept. The scale of the odometry is not
fitted: a loop returns to where it started, so a path a few percent too long closes
as well as the true one.

With no loops the rate is 0 and the odometry is returned as it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["fit_yaw_rate", "turn_steps", "PRIOR_DEG_PER_M"]

# Standard deviation of the prior on the heading drift (degrees per metre): wide
# against what odometries show (a few hundredths), narrow enough that a lone loop
# cannot turn the whole trajectory.
PRIOR_DEG_PER_M = 0.2
# The coarse search before the refinement: +-GRID_DEG_PER_M in GRID_STEPS steps, so
# that a start far from the loops' answer (every loop metres off) cannot stall it.
GRID_DEG_PER_M = 0.5
GRID_STEPS = 51


def turn_steps(odometry: np.ndarray, rate: float) -> np.ndarray:
    """`odometry` `[N, 4, 4]` chained again from its first pose with each step's
    rotation turned about z by `-rate` radians per metre of the step."""
    odo = np.asarray(odometry, dtype=np.float64)
    if rate == 0.0 or len(odo) < 2:
        return odo.copy()
    steps = np.linalg.inv(odo[:-1]) @ odo[1:]
    angle = -rate * np.linalg.norm(steps[:, :3, 3], axis=1)
    c, s = np.cos(angle), np.sin(angle)
    turn = np.zeros((len(angle), 3, 3))
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1] = c, -s, s, c
    turn[:, 2, 2] = 1.0
    steps[:, :3, :3] = turn @ steps[:, :3, :3]
    out = np.empty_like(odo)
    out[0] = odo[0]
    for i in range(len(steps)):
        out[i + 1] = out[i] @ steps[i]
    return out


def _rotvecs(R: np.ndarray) -> np.ndarray:
    """Rotation vectors `[K, 3]` of rotations `[K, 3, 3]` (small angles: all a loop's
    error is, once its pose is near)."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    sin = np.sin(angle)
    scale = np.where(sin > 1e-9, angle / np.maximum(2.0 * sin, 1e-12), 0.5)
    return axis * scale[:, None]


def fit_yaw_rate(
    odometry: np.ndarray,
    loops: Sequence[tuple[int, int, np.ndarray, np.ndarray]],
    *,
    width: float = 3.0,
    robust: bool = True,
) -> float:
    """The yaw per metre (radians) whose removal best closes `loops` ((match, query,
    T_match<-query, 6 x 6 information rotation first)) along `odometry`; each loop's
    whitened error under a Cauchy loss `width` sigmas wide (`robust`; else squares),
    plus the prior. 0.0 without loops."""
    if not loops:
        return 0.0
    j = np.array([lp[0] for lp in loops])
    i = np.array([lp[1] for lp in loops])
    inv_T = np.linalg.inv(np.stack([lp[2] for lp in loops]))
    # Whitening: W with W.T @ W = information, so |W e|^2 is the loop's squared sigmas.
    W = np.stack([np.linalg.cholesky(lp[3] + 1e-12 * np.eye(6)).T for lp in loops])
    prior = math.radians(PRIOR_DEG_PER_M)

    def cost(rate: float) -> float:
        P = turn_steps(odometry, rate)
        E = inv_T @ np.linalg.inv(P[j]) @ P[i]
        e = np.concatenate([_rotvecs(E[:, :3, :3]), E[:, :3, 3]], axis=1)
        r2 = np.sum(np.einsum("kab,kb->ka", W, e) ** 2, axis=1)
        loss = width**2 * np.log1p(r2 / width**2) if robust else r2
        return float(np.sum(loss) + (rate / prior) ** 2)

    grid = np.linspace(-1.0, 1.0, GRID_STEPS) * math.radians(GRID_DEG_PER_M)
    costs = [cost(float(r)) for r in grid]
    k = int(np.argmin(costs))
    # Golden-section refinement inside the best grid cell's neighbours.
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(30):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = cost(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = cost(b)
    best = (lo + hi) / 2.0
    return float(best) if cost(best) <= costs[k] else float(grid[k])
