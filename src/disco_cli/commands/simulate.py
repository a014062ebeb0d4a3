"""`disco simulate`: write sessions of a synthetic LiDAR town in KITTI layout.

Each session `OUT/00`, `OUT/01`, ... holds `velodyne/NNNNNN.bin` scans, `poses.txt`
(sensor poses in the town's frame, shared by all sessions) and `times.txt`;
`OUT/world.json` records every parameter, so the same command writes the same bytes.
"""

from __future__ import annotations

from dataclasses import replace
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import QuietOpt, ThreadsOpt
from disco_cli.runtime.console import fail, handle_errors, progress, stderr


class Style(str, Enum):
    grid = "grid"
    suburban = "suburban"
    industrial = "industrial"
    park = "park"
    parking = "parking"
    terrace = "terrace"
    boulevard = "boulevard"


class Terrain(str, Enum):
    flat = "flat"
    varied = "varied"


def _range(text: str) -> tuple[float, float]:
    """`LO,HI` or one value, as a range of two floats."""
    try:
        parts = [float(v) for v in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"{text!r} is not a number or LO,HI") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or parts[0] > parts[1]:
        raise typer.BadParameter(f"{text!r} is not LO,HI with LO <= HI")
    return parts[0], parts[1]


@handle_errors
def simulate(
    out: Annotated[
        Path,
        typer.Argument(
            help="Output folder (sessions 00, 01, ... and world.json).", file_okay=False
        ),
    ],
    sessions: Annotated[
        int,
        typer.Option(
            "--sessions", min=1, max=99, help="How many sessions to drive through the town."
        ),
    ] = 2,
    frames: Annotated[
        Optional[int], typer.Option("--frames", min=1, help="Scans per session.")
    ] = None,
    length_m: Annotated[
        Optional[float],
        typer.Option(
            "--length-m",
            min=1.0,
            help="Session length in metres (instead of --frames; default 400).",
        ),
    ] = None,
    step_m: Annotated[
        float, typer.Option("--step-m", min=0.05, help="Mean distance driven between scans (m).")
    ] = 1.0,
    sensor: Annotated[
        str,
        typer.Option(
            "--sensor",
            help="Beam pattern to simulate: hdl32, hdl64, vlp16, os1-64, or a made-up "
            "uniform-N or hdl64like-N (N = 16..128 beams; see docs/simulator.md).",
        ),
    ] = "hdl32",
    seed: Annotated[int, typer.Option("--seed", min=0, help="World and noise seed.")] = 0,
    azimuth_step: Annotated[
        Optional[float],
        typer.Option("--azimuth-step", help="Azimuth step in degrees (default: the sensor's own)."),
    ] = None,
    town: Annotated[
        Optional[Path],
        typer.Option(
            "--town",
            exists=True,
            dir_okay=False,
            help="Town parameters: a TOML file (see docs/simulator.md) or an earlier world.json.",
        ),
    ] = None,
    motion_distortion: Annotated[
        bool,
        typer.Option(
            "--motion-distortion",
            help="Raw scans: each ray from where the sensor was when it "
            "fired (default: deskewed, every ray from the scan's pose).",
        ),
    ] = False,
    style: Annotated[
        Optional[Style],
        typer.Option(
            "--style",
            help="Town style: grid (mixed streets, the default), suburban, industrial, "
            "park, parking, terrace (rows of alike houses) or boulevard (a street alike "
            "on both sides).",
            rich_help_panel="World",
        ),
    ] = None,
    terrain: Annotated[
        Optional[Terrain],
        typer.Option(
            "--terrain",
            help="flat (default) or varied: crowned roads, high kerbs, hills.",
            rich_help_panel="World",
        ),
    ] = None,
    change: Annotated[
        Optional[float],
        typer.Option(
            "--change",
            min=0.0,
            max=1.0,
            help="Share of each class of objects (parked cars, trees, hedges, fences, "
            "street furniture; buildings a fifth of it) that differs between session 00 "
            "and each later one (default: the classic draw).",
            rich_help_panel="World",
        ),
    ] = None,
    wobble: Annotated[
        float,
        typer.Option(
            "--wobble",
            min=0.0,
            max=10.0,
            help="Every session: the platform rolls and pitches from scan to scan, "
            "within +-DEG (a smooth random walk, as a Segway's; docs/simulator.md).",
            rich_help_panel="World",
        ),
    ] = 0.0,
    robot_height: Annotated[
        Optional[str],
        typer.Option(
            "--robot-height",
            metavar="LO,HI",
            help="Later sessions: sensor mount height above the ground, drawn in LO..HI m.",
            rich_help_panel="Later sessions' robots",
        ),
    ] = None,
    robot_tilt: Annotated[
        float,
        typer.Option(
            "--robot-tilt",
            min=0.0,
            max=10.0,
            help="Later sessions: the mount's roll and pitch, each drawn within +-DEG.",
            rich_help_panel="Later sessions' robots",
        ),
    ] = 0.0,
    robot_offset: Annotated[
        Optional[float],
        typer.Option(
            "--robot-offset",
            min=0.0,
            help="Later sessions: drive up to this far (m) sideways from session 00's line.",
            rich_help_panel="Later sessions' robots",
        ),
    ] = None,
    robot_jitter: Annotated[
        float,
        typer.Option(
            "--robot-jitter",
            min=0.0,
            max=5.0,
            help="Later sessions: each scan moved by up to +-M m along and across its "
            "driving line (uniform, per scan).",
            rich_help_panel="Later sessions' robots",
        ),
    ] = 0.0,
    robot_side: Annotated[
        Optional[str],
        typer.Option(
            "--robot-side",
            metavar="LO,HI",
            help="Later sessions: drive LO..HI m to the side of session 00's line "
            "(instead of --robot-offset; the road must be that wide).",
            rich_help_panel="Later sessions' robots",
        ),
    ] = None,
    robot_sensor: Annotated[
        Optional[str],
        typer.Option(
            "--robot-sensor",
            help="Later sessions' sensor: a --sensor name, uniform-N or hdl64like-N "
            "(N = 16..128 beams), or random (16/32/64/128 beams, either layout).",
            rich_help_panel="Later sessions' robots",
        ),
    ] = None,
    odometry_drift: Annotated[
        Optional[str],
        typer.Option(
            "--odometry-drift",
            metavar="SCALE,YAW[,NOISE_M[,NOISE_DEG]]",
            help="Also write odometry.txt beside each session's poses.txt: the true steps "
            "with a scale error (0.02: 2 % long), a yaw bias in degrees a step, and "
            "noise per step (default 0.01 m, 0.02 deg), seeded by --seed "
            "(for disco correct; docs/correct.md).",
            rich_help_panel="Odometry",
        ),
    ] = None,
    join: Annotated[
        bool,
        typer.Option(
            "--join",
            help="Also write OUT/joined: every session one after the other as one "
            "sequence, with poses.txt, times.txt and odometry.txt (drifted as "
            "--odometry-drift says, by default 0.02,0.04).",
            rich_help_panel="Odometry",
        ),
    ] = False,
    threads: ThreadsOpt = None,
    force: Annotated[
        bool, typer.Option("--force", help="Write into a folder that has sessions.")
    ] = False,
    quiet: QuietOpt = False,
) -> None:
    """Simulate a LiDAR driving through a procedural town, in several sessions."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    threads = set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: numpy and the simulator (~0.2 s) load when the command runs, not for --help
    from disco_cli.simulator import ChangeParams, RobotParams, TownParams
    from disco_cli.simulator import simulate as run
    from disco_cli.simulator.odometry_drift import Drift, write_odometry

    if frames is not None and length_m is not None:
        raise fail("give --frames or --length-m, not both")
    if out.exists() and (out / "world.json").exists() and not force:
        raise fail(f"{out}: already holds a simulated world; use --force to overwrite it")
    drift = Drift.parse(odometry_drift, seed) if odometry_drift is not None else None
    if join and drift is None:
        drift = Drift(seed=seed)
    params = TownParams.load(town) if town is not None else None
    if style is not None or terrain is not None or change is not None:
        params = params or TownParams()
        if style is not None:
            params = replace(params, style=style.value)
        if terrain is not None:
            params = replace(params, terrain=terrain.value)
        if change is not None:  # the town file's own per-class shares stay
            base = params.change or ChangeParams()
            params = replace(params, change=replace(base, fraction=float(change)))
    robot = None
    if (
        robot_height
        or robot_tilt
        or robot_offset is not None
        or robot_sensor
        or robot_jitter
        or robot_side
    ):
        robot = RobotParams(
            height_m=_range(robot_height) if robot_height else None,
            tilt_deg=float(robot_tilt),
            offset_m=robot_offset,
            sensor=robot_sensor,
            jitter_m=float(robot_jitter),
            side_m=_range(robot_side) if robot_side else None,
        )
    total = sessions * (frames if frames is not None else int((length_m or 400.0) / step_m))
    with progress() as bar:
        task = bar.add_task("simulating", total=total, rate="", unit="scans")

        def report(done: int, _total: int) -> None:
            bar.update(task, completed=done)

        meta = run(
            out,
            sessions=sessions,
            frames=frames,
            length_m=length_m,
            step_m=step_m,
            sensor=sensor,
            seed=seed,
            threads=threads,
            azimuth_step_deg=azimuth_step,
            motion_distortion=motion_distortion,
            params=params,
            on_scan=report,
            robot=robot,
            wobble_deg=float(wobble),
        )
    if drift is not None:
        write_odometry(out, drift, join=join)
    n = meta["sessions"][0]["frames"]
    stderr.print(
        f"wrote {sessions} session(s) of {n} {sensor} scans to {out} "
        f"(town of {meta['town']['streets']} streets, seed {seed})"
    )
