"""Pictures of a polar BEV, for `disco bev`: which points it counts, one value per cell,
and the cells drawn as rings x sectors or as a top-down disc (PNG colours: `png.py`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from disco_cli.io.png import BACKGROUND, colormap, upscale

__all__ = ["in_window", "collapse", "rect_image", "polar_image", "picture"]

# The longer side of the sectors x rings picture when no scale is given, and the most.
_TARGET_WIDTH = 960
_MAX_SIDE = 4096
_GREY = (96, 96, 96)
_WHITE = (255, 255, 255)


def in_window(points: np.ndarray, config: Any) -> np.ndarray:
    """Mask of the points that the BEV counts: finite, `min_range <= r < max_range`
    and `z_min <= z < z_max` (the voxelizer's window, in double precision)."""
    xyz = np.asarray(points[:, :3], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        r = np.hypot(xyz[:, 0], xyz[:, 1])
        z = xyz[:, 2]
        return (
            np.isfinite(xyz).all(axis=1)
            & (r >= config.min_range)
            & (r < config.max_range)
            & (z >= config.z_min)
            & (z < config.z_max)
        )


def collapse(bev: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, str]:
    """One value in [0, 1] per (ring, sector) cell, the mask of empty cells, and
    what the top of the colour scale stands for.

    Each column of height layers becomes one number: occupancy counts occupied
    layers, density sums the layers, max_height takes the top point's height.
    Values are relative to the scan's largest, so that a scan with low objects
    still uses the whole colour scale; density is shown on a square-root scale
    because near rings hold far more points than far ones.
    """
    if mode == "max_height":
        column = bev.max(axis=0).astype(np.float64)
    else:
        column = bev.sum(axis=0, dtype=np.float64)
    empty = column <= 0
    peak = float(column.max())
    if peak <= 0:
        return np.zeros_like(column), empty, "empty"
    if mode == "occupancy":
        return column / peak, empty, f"{peak:g} of {bev.shape[0]} layers occupied"
    if mode == "density":
        return np.sqrt(column / peak), empty, "the densest column, square-root scale"
    return column / peak, empty, f"{peak:.2f} m above z_min"


def rect_image(values: np.ndarray, empty: np.ndarray, scale: int) -> np.ndarray:
    """RGB picture: rings as rows (nearest at the top), sectors as columns (sector 0,
    straight ahead, at the left; angles grow to the right), each cell a
    `scale x scale` block."""
    return upscale(colormap(values, empty), scale)


def polar_image(values: np.ndarray, empty: np.ndarray, config: Any, scale: int) -> np.ndarray:
    """RGB top-down disc: the sensor at the centre, +x (ahead) up, +y (left) to the
    left, as seen from above; `2 * rings * scale` pixels across."""
    rings, sectors = values.shape
    size = 2 * rings * scale
    metres_per_px = config.max_range / (size / 2)
    centre = size / 2
    # The BEV cell under each pixel centre, by the voxelizer's own formulas.
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64) + 0.5
    x = (centre - rows) * metres_per_px
    y = (centre - cols) * metres_per_px
    r = np.hypot(x, y)
    theta = np.mod(np.arctan2(y, x), 2 * np.pi)
    ring = np.minimum((r / (config.max_range / rings)).astype(np.int64), rings - 1)
    sector = np.minimum((theta / (2 * np.pi / sectors)).astype(np.int64), sectors - 1)
    image = colormap(values[ring, sector], empty[ring, sector])
    image[(r < config.min_range) | (r >= config.max_range)] = BACKGROUND
    # Landmarks: the edge of the window as a grey circle, and a white line from
    # the sensor to min_range pointing ahead (+x).
    image[np.abs(r - config.max_range) < metres_per_px] = _GREY
    ahead = (np.abs(y) < metres_per_px) & (x >= 0) & (r < config.min_range)
    image[ahead] = _WHITE
    return image


def picture(
    grid: np.ndarray, mode: str, config: Any, polar: bool = False, scale: int | None = None
) -> tuple[np.ndarray, str]:
    """The RGB picture of a BEV `grid` whose cells hold `mode` (`polar_image` or
    `rect_image`, `scale` pixels per cell; default: about 960 pixels wide), and what
    the top of its colour scale stands for (`collapse`)."""
    values, empty, top = collapse(grid, mode)
    cells_across = 2 * grid.shape[1] if polar else grid.shape[2]
    if scale is None:
        scale = max(1, round(_TARGET_WIDTH / cells_across))
    # Keep the picture (and the memory it takes) within reason for big grids.
    scale = max(1, min(scale, _MAX_SIDE // cells_across))
    if polar:
        return polar_image(values, empty, config, scale), top
    return rect_image(values, empty, scale), top
