"""`disco bev`: read one scan and write its polar BEV as a picture or a raw array.

This is the first command a new user runs, to see that their scans are read
the right way: it says how many points it read and how many fell inside the
BEV window, and draws the BEV so that a wrong format or unit is plain to see.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from disco_cli.commands.options import ScanFormatOpt, TopicOpt, model_option, output_option
from disco_cli.console import fail, handle_errors, stderr, warn

if TYPE_CHECKING:
    import numpy as np

# The longer side of the sectors x rings picture when --scale is not given.
_TARGET_WIDTH = 960
_MAX_SIDE = 4096
_GREY = (96, 96, 96)
_WHITE = (255, 255, 255)


class BEVMode(str, Enum):
    occupancy = "occupancy"
    density = "density"
    max_height = "max_height"


def in_window(points: np.ndarray, config: Any) -> np.ndarray:
    """Mask of the points that the BEV counts: finite, `min_range <= r < max_range`
    and `z_min <= z < z_max` (the voxelizer's window, in double precision)."""
    import numpy as np

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
    import numpy as np

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
    from disco_cli.png import colormap, upscale

    return upscale(colormap(values, empty), scale)


def polar_image(values: np.ndarray, empty: np.ndarray, config: Any, scale: int) -> np.ndarray:
    """RGB top-down disc: the sensor at the centre, +x (ahead) up, +y (left) to the
    left, as seen from above; `2 * rings * scale` pixels across."""
    import numpy as np

    from disco_cli.png import BACKGROUND, colormap

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


def _write(output: Path, save: Any) -> None:
    """Run `save()` after making the output's folder; one error line if that fails."""
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        save()
    except OSError as exc:
        raise fail(f"{output}: cannot write ({exc.strerror or exc})") from None


@handle_errors
def bev(
    scan: Annotated[
        Path,
        typer.Argument(
            help="The scan file (.bin, .npy, .pcd, .ply), a scan in a ROS bag "
            "(BAG#TOPIC@STAMP_NS), or a bag (its first scan)."
        ),
    ],
    output: Annotated[
        Path, output_option("Where to write: .png for a picture, .npy for the raw array.")
    ],
    scan_format: ScanFormatOpt = None,
    mode: Annotated[
        BEVMode | None,
        typer.Option("--bev-mode", help="What each cell holds; default: the BEV config's."),
    ] = None,
    scale: Annotated[
        int | None,
        typer.Option(
            "--scale",
            "-s",
            min=1,
            max=64,
            help="Pixels per BEV cell in the PNG; default: about 960 pixels wide.",
        ),
    ] = None,
    polar: Annotated[
        bool,
        typer.Option("--polar", help="Draw the PNG as a top-down disc instead of rings x sectors."),
    ] = False,
    model: Annotated[
        str | None,
        model_option(
            "Use this model's BEV config (a name such as spectral, or a checkpoint), "
            "to see what it sees; default: the built-in BEV config.",
            panel=None,
        ),
    ] = None,
    topic: TopicOpt = None,
) -> None:
    """Write the polar BEV of one scan: check that your data is read correctly."""
    suffix = output.suffix.lower()
    if suffix not in (".png", ".npy"):
        raise fail(f"{output}: the output must end in .png or .npy")
    if polar and suffix != ".png":
        raise fail("--polar draws a picture: give an output ending in .png")

    import dataclasses

    import numpy as np

    from disco_cli.bev import BEVConfig, polar_bev
    from disco_cli.readers import guess_format, is_bag, list_scans, read_scan

    if is_bag(scan):
        scan = list_scans(scan, topic=topic)[0]
    points = read_scan(scan, format=scan_format)
    fmt = scan_format.value if scan_format else guess_format(scan)
    if model is not None:
        from disco_cli.model import load_model

        config = load_model(model).bev_config
    else:
        config = BEVConfig()
    if mode is not None:
        config = dataclasses.replace(config, mode=mode.value)
    used = int(in_window(points, config).sum())
    stderr.print(
        f"read {len(points)} points ({fmt}) from {scan}; {used} in the BEV window "
        f"({config.min_range:g} <= r < {config.max_range:g} m, "
        f"{config.z_min:g} <= z < {config.z_max:g} m)",
        soft_wrap=True,
    )
    if used == 0:
        warn("no point falls in the BEV window: wrong format, units (mm?) or sensor height?")
    elif used < 0.2 * len(points):
        warn(f"only {100 * used / len(points):.0f}% of the points fall in the BEV window")

    grid = polar_bev(points, config)
    cell_mode = str(getattr(config.mode, "value", config.mode))
    shape = "[" + ", ".join(str(n) for n in grid.shape) + "]"
    if suffix == ".npy":
        _write(output, lambda: np.save(output, grid))
        what = f"BEV {shape} float32 ({cell_mode})"
    else:
        from disco_cli.png import write_png

        values, empty, top = collapse(grid, cell_mode)
        cells_across = 2 * grid.shape[1] if polar else grid.shape[2]
        if scale is None:
            scale = max(1, round(_TARGET_WIDTH / cells_across))
        # Keep the picture (and the memory it takes) within reason for big grids.
        scale = max(1, min(scale, _MAX_SIDE // cells_across))
        if polar:
            image = polar_image(values, empty, config, scale)
        else:
            image = rect_image(values, empty, scale)
        _write(output, lambda: write_png(output, image))
        what = (
            f"BEV {shape} ({cell_mode}) as a {image.shape[1]} x {image.shape[0]} "
            f"{'top-down' if polar else 'sectors x rings'} picture (yellow: {top})"
        )
    occupied = int((grid.reshape(grid.shape[0], -1) > 0).any(axis=0).sum())
    stderr.print(
        f"wrote {output}: {what}; {used} points in {occupied} of "
        f"{grid.shape[1] * grid.shape[2]} ring x sector cells",
        soft_wrap=True,
    )
