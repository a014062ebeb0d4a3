"""Where each view of a polar image re-centred on a position reads it: the polar grid's
Cartesian centres (`grid`), and each cell's fractional ring and sector computed by the
compiled core (`compiled`, `_core.recentre_places`). `yaw_refine._places` computes the
same in NumPy (the reference): rings to the bit, sectors within a float32 ulp or two
(the core's arctan2 is correctly rounded but for about 1 cell in 5 million; NumPy's
float32 arctan2 is not, by up to 3 ulps where it runs on AVX-512).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np


@lru_cache(maxsize=8)
def grid(rings: int, sectors: int, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian centres (x, y) [R, S] of the polar cells, in m."""
    dr = max_range / rings
    r = (np.arange(rings) + 0.5) * dr
    theta = (np.arange(sectors) + 0.5) * (2.0 * np.pi / sectors)
    x = (r[:, None] * np.cos(theta)[None]).astype(np.float32)
    y = (r[:, None] * np.sin(theta)[None]).astype(np.float32)
    return x, y


@lru_cache(maxsize=8)
def _flat_grid(rings: int, sectors: int, max_range: float, lanes: bool) -> tuple:
    """`grid` flat, ring-major ([R * S]) or sector-major ([S * R], `lanes`): the order
    the places come out in."""
    x, y = grid(rings, sectors, max_range)
    if lanes:
        x, y = x.T, y.T
    return np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel()


def compiled(
    core: Any, rings: int, sectors: int, max_range: float, positions: np.ndarray, lanes: bool
) -> list:
    """`yaw_refine._places` of `positions` [M, 2] by `core.recentre_places`: per position,
    float32 [2, R * S], or [2, S * R] sector-major (`lanes`: `yaw_refine._lane_places`)."""
    x, y = _flat_grid(rings, sectors, max_range, lanes)
    pos = np.ascontiguousarray(np.asarray(positions, dtype=np.float32).reshape(-1, 2))
    # The constants as NumPy's float32 arithmetic in `_places` rounds them.
    out = core.recentre_places(
        x, y, pos, np.float32(rings / max_range), np.float32(rings + 1),
        np.float32(sectors / (2.0 * np.pi)), np.float32(sectors - 0.5),
    )  # fmt: skip
    return list(out)
