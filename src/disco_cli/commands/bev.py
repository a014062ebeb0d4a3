"""`disco bev`: read one scan and write its polar BEV as a picture or a raw array.

This is the first command a new user runs, to see that their scans are read
the right way: it says how many points it read and how many fell inside the
BEV window, and draws the BEV so that a wrong format or unit is plain to see.
"""

from __future__ import annotations

import dataclasses
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from disco_cli.commands.options import ScanFormatOpt, TopicOpt, model_option, output_option
from disco_cli.io import readers
from disco_cli.io.readers import guess_format, is_bag, list_scans
from disco_cli.runtime.console import fail, handle_errors, stderr, warn


class BEVMode(str, Enum):
    occupancy = "occupancy"
    density = "density"
    max_height = "max_height"


def _write(output: Path, save: Any) -> None:
    """`save(tmp)`, renamed onto `output`; one error line if that fails."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.io.output_paths import write_atomic

    write_atomic(output, save)


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
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.io.output_paths import check_output_file

    check_output_file(output, what="the BEV")

    # deferred: numpy and the voxelizer (~0.2 s) load when the command runs, not for --help
    import numpy as np

    from disco_cli.io.bev_image import in_window, picture
    from disco_cli.model.bev import BEVConfig, polar_bev

    if is_bag(scan):
        scan = list_scans(scan, topic=topic)[0]
    points = readers.read_scan(scan, format=scan_format)  # tests replace read_scan
    fmt = scan_format.value if scan_format else guess_format(scan)
    if model is not None:
        from disco_cli.model import load_model  # deferred: --model only, not for --help

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
        _write(output, lambda tmp: np.save(tmp, grid))
        what = f"BEV {shape} float32 ({cell_mode})"
    else:
        from disco_cli.io.png import write_png  # deferred: .png output only, not for --help

        image, top = picture(grid, cell_mode, config, polar, scale)
        _write(output, lambda tmp: write_png(tmp, image))
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
