"""`disco build-db`: embed scans into a map database, one transaction per batch.

Ctrl-C or a crash keeps every finished batch; running the same command again
resumes, skipping the scans already stored (by absolute path). The work is
`Map.add_files` (disco_cli/map.py).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_POSES,
    PANEL_RUN,
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    ScanFormatOpt,
    TopicOpt,
    WorkersOpt,
    model_option,
    opt,
    output_option,
    pose_options,
)
from disco_cli.console import fail, handle_errors, progress, stderr, warn

PANEL_IN = "Input"


@handle_errors
def build_db(
    inputs: Annotated[
        list[str],
        typer.Argument(
            help="Scan folders (KITTI-style DIR/velodyne/ or a folder of scans), scan files, "
            "or - to read scan paths from stdin, one per line.",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path, output_option("The database file to write (map.db).", panel=PANEL_IN)
    ] = Path("map.db"),
    model: Annotated[
        str, model_option("default, spectral, scancontext or a checkpoint path.", panel=PANEL_IN)
    ] = "default",
    poses: Annotated[
        Optional[Path],
        opt(
            "--poses",
            panel=PANEL_POSES,
            help="Poses of all scans (KITTI by frame, or by time: --poses-format); "
            "default: the pose file beside each folder's scans.",
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    times: Annotated[
        Optional[Path],
        opt(
            "--times",
            panel=PANEL_IN,
            help="Timestamps (s), one per scan; default: times.txt beside each folder's scans.",
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    append: Annotated[
        bool,
        opt(
            "--append",
            panel=PANEL_IN,
            help="Add these scans to an existing database built from other scans (same model).",
        ),
    ] = False,
    batch: Annotated[
        int,
        opt(
            "--batch",
            min=1,
            max=4096,
            panel=PANEL_RUN,
            help="Scans per network batch and per transaction.",
        ),
    ] = 32,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    skip_bad: Annotated[
        bool,
        opt(
            "--skip-bad",
            panel=PANEL_RUN,
            help="Warn about unreadable scans and go on, instead of stopping at the first.",
        ),
    ] = False,
) -> None:
    """Build (or resume, or extend) a map database from scans."""
    from disco_cli.errors import DatabaseError
    from disco_cli.map import Interrupted, Map
    from disco_cli.pipeline import check_device, collect_scans

    check_device(device)
    fmt = scan_format.value if scan_format is not None else None
    if pose_topic is not None and poses is not None:
        raise fail("give --poses or --pose-topic, not both")
    pose_opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    scans = collect_scans(inputs, poses, times, calib, fmt, pose_opts, warn, topic, pose_topic)
    if not scans.paths:
        raise fail("no scans given")
    absolute = {os.path.abspath(p) for p in scans.paths}
    if output.exists():
        m = Map.open(output, writable=True, model=model, device=device)
        stored = {os.path.abspath(p) for p in m.names()}  # an old map's relative paths too
        if not append and not stored.issubset(absolute):
            m.close()
            raise DatabaseError(
                output,
                "exists and holds other scans; pass --append to add to it, "
                "or choose another --output",
            )
    else:
        m, stored = Map.create(output, model, device=device), set()
    if absolute <= stored:
        stderr.print(f"{output}: all {len(absolute)} scans are in it already")
        m.close()
        return

    start = time.perf_counter()
    with m, progress() as bar:
        task = bar.add_task("build-db", total=len(absolute - stored), rate="")

        def advance(n_done: int, written: int) -> None:
            rate = written / max(time.perf_counter() - start, 1e-9)
            bar.update(task, completed=n_done, rate=f"{rate:.1f} scans/s")

        try:
            result = m.add_files(
                scans.paths,
                poses=scans.poses,
                times=scans.times,
                batch=batch,
                workers=workers,
                scan_format=fmt,
                skip_bad=skip_bad,
                on_progress=advance,
                on_skip=lambda exc: warn(f"skipped: {exc}"),
            )
        except Interrupted as stop:  # every committed batch is safe; say so, and how to go on
            if stop.added is None:
                stderr.print(f"interrupted: nothing written; {output} was not created")
            else:
                held = len(stored & absolute) + stop.added
                stderr.print(
                    f"interrupted: {output} holds {held} of the {len(absolute)} scans given, "
                    "safely stored; run the same command again to resume",
                    soft_wrap=True,
                )
            raise typer.Exit(130) from None
        created = m.database is not None
    elapsed = time.perf_counter() - start
    rate = result.written / max(elapsed, 1e-9)
    msg = f"{output}: wrote {result.written} scans in {elapsed:.1f} s ({rate:.1f} scans/s)"
    if result.already:
        msg += f", {result.already} were in it already"
    if scans.no_pose:
        msg += f", {scans.no_pose} without a pose"
    stderr.print(msg)
    if result.bad:
        warn(f"{len(result.bad)} unreadable scans skipped")
    if result.written == 0 and not created:
        raise fail(f"{output}: no readable scans; nothing written")
