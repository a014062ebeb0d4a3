"""`disco loops`: online loop-closure detection along one sequence.

Each scan is searched only against the scans at least N frames (or S seconds) before
it, as a robot would when it reaches that scan. The work is `LoopDetector.add_files`
(disco_cli/loop_detector.py), the class a Python program feeds scan by scan.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_OUT,
    PANEL_RUN,
    BatchOpt,
    DeviceOpt,
    ExcludeFramesOpt,
    ExcludeSecondsOpt,
    OutputFormatOpt,
    RerankOpt,
    ScanFormatOpt,
    ScanRootOpt,
    TimesOpt,
    TopicOpt,
    WorkersOpt,
    db_option,
    model_option,
    opt,
    output_option,
    topk_option,
)
from disco_cli.console import error, fail, handle_errors, progress, stderr, warn

COLUMNS = ["query_index", "query", "match_index", "match", "distance", "yaw_deg"]
ANGLE_COLUMNS = ["roll_deg", "pitch_deg"]  # with a pose; yaw_deg is then the refined yaw
POSE_COLUMNS = ["dx", "dy", "dz", "fitness", "rmse", "accepted", "reason"]
PANEL_POSE = "Relative pose"
_BLOCK = 64  # query scans whose loops are printed together (one table each)


@handle_errors
def loops(
    sequence: Annotated[
        Path,
        typer.Argument(
            show_default=False,
            help="The sequence: a folder of scans (KITTI-style "
            "DIR/velodyne/ or a folder of scan files), or a ROS bag.",
        ),
    ],
    exclude_frames: ExcludeFramesOpt = None,  # default 50
    exclude_seconds: ExcludeSecondsOpt = None,
    threshold: Annotated[
        Optional[float],
        opt(
            "--threshold",
            "-t",
            min=0.0,
            help="Report pairs with a distance at most this (the `distance` column); default: all.",
        ),
    ] = None,
    topk: Annotated[int, topk_option("Candidates per query scan.", max=1000)] = 1,
    model: Annotated[
        str, model_option("default, spectral, scancontext or a checkpoint path.", panel=None)
    ] = "default",
    fmt: OutputFormatOpt = None,
    verify: Annotated[
        bool,
        opt(
            "--verify",
            panel=PANEL_POSE,
            help="Estimate each pair's relative pose (phase "
            "correlation + ICP) and keep only the accepted ones: yaw_deg becomes the refined "
            "yaw, roll_deg and pitch_deg are added (JSON lines also carry the 4 x 4 T).",
        ),
    ] = False,
    verbose: Annotated[
        bool,
        opt(
            "--verbose",
            "-v",
            panel=PANEL_POSE,
            help="Estimate each pair's relative pose and "
            "show it (dx, dy, dz, fitness, rmse, accepted, reason), rejected pairs included "
            "unless --verify.",
        ),
    ] = False,
    output: Annotated[
        Optional[Path],
        output_option(
            "Also write the loops with their relative poses: .g2o (EDGE_SE3:QUAT, "
            "accepted loops only), .tum or .csv.",
            panel=PANEL_OUT,
        ),
    ] = None,
    times: TimesOpt = None,
    db_path: Annotated[
        Optional[Path],
        db_option(
            "Reuse the signatures of a database built from this sequence (same model); "
            "scans not in it are embedded.",
            panel=PANEL_RUN,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    scan_root: ScanRootOpt = None,
    batch: BatchOpt = 32,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
) -> None:
    """Detect loop closures along one sequence of scans (by default each scan searches the
    scans at least 50 frames before it)."""
    import numpy as np

    from disco_cli.console import RowWriter
    from disco_cli.loop_detector import LoopDetector
    from disco_cli.loop_export import check_loop_file, write_loops
    from disco_cli.map import Map
    from disco_cli.pipeline import sequence_times
    from disco_cli.readers import list_scans

    if exclude_frames is not None and exclude_seconds is not None:
        raise fail("give --exclude-frames or --exclude-seconds, not both")
    if output is not None:
        check_loop_file(output)
    with_pose = verify or verbose or output is not None
    paths = [str(p) for p in list_scans(sequence, scan_format, topic)]
    needs_times = with_pose or exclude_seconds is not None
    stamps = sequence_times(sequence, paths, times) if needs_times else None
    if exclude_seconds is not None:
        if stamps is None:
            raise fail(f"{sequence}: --exclude-seconds needs times.txt beside the scans or --times")
        if np.any(np.diff(stamps) < 0):
            warn(f"{sequence}: timestamps are not increasing; frames are taken in file order")

    pose_failures = []
    detector = LoopDetector(
        model,
        exclude_frames=None if exclude_seconds is not None else (exclude_frames or 50),
        exclude_seconds=exclude_seconds,
        threshold=threshold,
        verify=verify,
        pose=with_pose,
        topk=topk,
        rerank=rerank,
        device=device,
        on_pose_error=lambda msg: (error(msg), pose_failures.append(msg)),
    )
    columns = COLUMNS + (ANGLE_COLUMNS if with_pose else []) + (POSE_COLUMNS if verbose else [])
    writer = RowWriter(columns, fmt, title=f"loops in {sequence}")
    keys = columns + (["T"] if with_pose else [])
    found, block, reuse = [], [], None
    if db_path is not None:
        with Map.open(db_path, model=detector.model, scan_root=scan_root) as m:
            reuse = m.stored(paths)
        if not reuse[0].any():
            warn(f"{db_path}: holds none of these scans; embedding them all")
    with progress(transient=True) as bar:
        task = bar.add_task("loops", total=len(paths), rate="")
        stream = detector.add_files(
            paths,
            times=stamps,
            stored=reuse,
            batch=batch,
            workers=workers,
            scan_format=scan_format,
            on_progress=lambda k: bar.advance(task, k),
        )
        for i, new in enumerate(stream):
            found += new
            block += [{k: lp.as_dict()[k] for k in keys} for lp in new]
            if block and ((i + 1) % _BLOCK == 0 or i + 1 == len(paths)):
                writer.write(block)
                block = []
    if not found:
        writer.write([])  # the header (an empty table), so that "no loop" reads as an answer
    stderr.print(f"{sequence}: {len(found)} loop candidates among {len(paths)} scans")
    if output is not None:
        stderr.print(f"{output}: {write_loops(output, found)} loops written")
    if pose_failures:
        raise typer.Exit(1)
