"""`disco build-db`: embed scans into a map database, one transaction per batch.

Ctrl-C or a crash keeps every finished batch; running the same command again
resumes, skipping the scans already stored (by absolute path). The work is
`Map.add_files` (disco_cli/maps/writing.py).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_IN,
    PANEL_POSES,
    AppendOpt,
    CalibOpt,
    CopyFromOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    QuietOpt,
    RepairOpt,
    ScanFormatOpt,
    SideViewsOpt,
    SkipBadOpt,
    ThreadsOpt,
    TopicOpt,
    batch_option,
    model_option,
    output_option,
    pose_options,
    poses_option,
    times_option,
)
from disco_cli.runtime.console import fail, handle_errors, plural, rate_bar, say, stderr, warn

MODEL_OF_NEW_MAP = "default, spectral, scancontext or a checkpoint; default: an existing map's."


@handle_errors
def build_db(
    inputs: Annotated[
        Optional[list[str]],
        typer.Argument(
            help="Scan folders (KITTI-style DIR/velodyne/ or a folder of scans), scan files, "
            "or - to read scan paths from stdin, one per line.",
            show_default=False,
        ),
    ] = None,
    output: Annotated[
        Path, output_option("The database file to write (map.db).", panel=PANEL_IN)
    ] = Path("map.db"),
    model: Annotated[Optional[str], model_option(MODEL_OF_NEW_MAP, panel=PANEL_IN)] = None,
    poses: Annotated[Optional[Path], poses_option(PANEL_POSES)] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    times: Annotated[Optional[Path], times_option(PANEL_IN)] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    append: AppendOpt = False,
    copy_from: CopyFromOpt = None,
    repair: RepairOpt = False,
    side_views: SideViewsOpt = None,
    batch: Annotated[int, batch_option("Scans per network batch and per transaction.")] = 32,
    threads: ThreadsOpt = None,
    device: DeviceOpt = "cpu",
    skip_bad: SkipBadOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Build (or resume, or extend) a map database from scans."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: numpy and the map code (~0.2 s) load when the command runs, not for --help
    from disco_cli.io.output_paths import check_map_output
    from disco_cli.io.scan_inputs import collect_scans
    from disco_cli.maps.build import open_for_adding, repair_files
    from disco_cli.maps.writing import Interrupted
    from disco_cli.model import check_device

    check_device(device)
    if copy_from is not None:  # a copy between stores: nothing is embedded
        from disco_cli.maps.milvus_copy import copy_command  # deferred: --copy-from only

        return say(copy_command(copy_from, output, inputs, warn))
    inputs = inputs or []
    output = check_map_output(output)  # before any scan is embedded
    fmt = scan_format.value if scan_format is not None else None
    if pose_topic is not None and poses is not None:
        raise fail("give --poses or --pose-topic, not both")
    pose_opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    scans = collect_scans(inputs, poses, times, calib, fmt, pose_opts, warn, topic, pose_topic)
    if not scans.paths:
        raise fail("no scans given")
    if repair:  # rewrite the damaged rows only (docs/database.md)
        done = repair_files(output, scans, model, fmt, batch, threads, device)
        return stderr.print(done, soft_wrap=True)
    # An existing map (resumed or --append) keeps its own model unless --model names one.
    chosen = model if model is not None or output.exists() else "default"
    m, given, held = open_for_adding(
        output, scans.paths, chosen, append=append, device=device, side_views=side_views
    )
    if m.database is not None and m.database.migrated is not None:
        stderr.print(m.database.migrated_line(), soft_wrap=True)
    if held == given:
        m.close()
        say(f"{output}: all {plural(given, 'scan')} are in it already")
        return

    start = time.perf_counter()
    with m, rate_bar("build-db", given - held) as advance:
        try:
            result = m.add_files(
                scans.paths,
                poses=scans.poses,
                times=scans.times,
                batch=batch,
                threads=threads,
                scan_format=fmt,
                skip_bad=skip_bad,
                on_progress=advance,
                on_skip=lambda exc: warn(f"skipped: {exc}"),
            )
        except Interrupted as stop:  # every committed batch is safe; say so, and how to go on
            stderr.print(stop.report(output, given, held), soft_wrap=True)
            raise typer.Exit(130) from None
        created = m.database is not None
    msg = f"{output}: {result.summary(time.perf_counter() - start)}"
    if scans.no_pose:
        msg += f", {scans.no_pose} without a pose"
    say(msg)
    if result.bad:
        warn(f"{plural(len(result.bad), 'unreadable scan')} skipped")
    if result.written == 0 and not created:
        raise fail(f"{output}: no readable scans; nothing written")
