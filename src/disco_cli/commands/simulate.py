"""`disco simulate`: write sessions of a synthetic LiDAR town in KITTI layout.

Each session `OUT/00`, `OUT/01`, ... holds `velodyne/NNNNNN.bin` scans, `poses.txt`
(sensor poses in the town's frame, shared by all sessions) and `times.txt`;
`OUT/world.json` records every parameter, so the same command writes the same bytes.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.console import fail, handle_errors, progress, stderr


class SensorName(str, Enum):
    hdl32 = "hdl32"
    hdl64 = "hdl64"
    vlp16 = "vlp16"
    os1_64 = "os1-64"


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
        SensorName, typer.Option("--sensor", help="Beam pattern to simulate.")
    ] = SensorName.hdl32,
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
    threads: Annotated[
        int, typer.Option("--threads", min=0, help="Ray-casting threads (0: all cores).")
    ] = 0,
    force: Annotated[
        bool, typer.Option("--force", help="Write into a folder that has sessions.")
    ] = False,
) -> None:
    """Simulate a LiDAR driving through a procedural town, in several sessions."""
    from disco_cli.simulator import TownParams
    from disco_cli.simulator import simulate as run

    if frames is not None and length_m is not None:
        raise fail("give --frames or --length-m, not both")
    if out.exists() and (out / "world.json").exists() and not force:
        raise fail(f"{out}: already holds a simulated world; use --force to overwrite it")
    params = TownParams.load(town) if town is not None else None
    total = sessions * (frames if frames is not None else int((length_m or 400.0) / step_m))
    with progress() as bar:
        task = bar.add_task("simulating", total=total, rate="")

        def report(done: int, _total: int) -> None:
            bar.update(task, completed=done)

        meta = run(
            out,
            sessions=sessions,
            frames=frames,
            length_m=length_m,
            step_m=step_m,
            sensor=sensor.value,
            seed=seed,
            threads=threads,
            azimuth_step_deg=azimuth_step,
            motion_distortion=motion_distortion,
            params=params,
            on_scan=report,
        )
    n = meta["sessions"][0]["frames"]
    stderr.print(
        f"wrote {sessions} session(s) of {n} {sensor.value} scans to {out} "
        f"(town of {meta['town']['streets']} streets, seed {seed})"
    )
