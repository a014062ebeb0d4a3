"""`disco eval-loops`: loop closure along one sequence against ground-truth poses.

The single-sequence protocol used on KITTI: every scan against the scans at least an
exclusion window before it. The work is `evaluation.runs.loop_closure`.
Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.evaluate import (
    PANEL_INPUT,
    PANEL_PROTOCOL,
    FormatOpt,
    RadiusOpt,
    ReportOpt,
    _bar,
    _report_and_print,
)
from disco_cli.commands.options import (
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    RerankOpt,
    ScanFormatOpt,
    TopicOpt,
    apply_rerank,
    model_option,
    opt,
    pose_options,
)
from disco_cli.console import handle_errors


@handle_errors
def evaluate_loops(
    sequence: Annotated[
        list[Path],
        typer.Argument(
            help="One sequence: a folder (velodyne/ layout) or its scans in order.",
            show_default=False,
        ),
    ],
    poses: Annotated[
        Optional[Path],
        opt("--poses", help="Poses; default: the pose file in the folder.", panel=PANEL_INPUT),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    times: Annotated[
        Optional[Path],
        opt(
            "--times",
            panel=PANEL_INPUT,
            help="Timestamps, one per scan; default: times.txt in the folder.",
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    model_name: Annotated[
        str,
        model_option("default, spectral, scancontext or a checkpoint path.", panel=PANEL_PROTOCOL),
    ] = "default",
    radius: RadiusOpt = 3.0,
    exclude_seconds: Annotated[
        Optional[float],
        opt(
            "--exclude-seconds",
            min=0.0,
            panel=PANEL_PROTOCOL,
            help="Search only scans at least this long before (default 30; needs times).",
        ),
    ] = None,
    exclude_frames: Annotated[
        Optional[int],
        opt(
            "--exclude-frames",
            min=1,
            panel=PANEL_PROTOCOL,
            help="Search only scans at least N frames before.",
        ),
    ] = None,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    report: ReportOpt = None,
    fmt: FormatOpt = None,
) -> None:
    """Loop closure along one sequence: precision-recall, F1max, recall at 100% precision."""
    import numpy as np

    from disco_cli.console import warn
    from disco_cli.errors import DiscoError, PoseFileError
    from disco_cli.evaluation.runs import exclusion_limits, loop_closure, posed_scans
    from disco_cli.model import load_model
    from disco_cli.pipeline import file_beside, frame_rows, scan_paths
    from disco_cli.poses import read_times
    from disco_cli.readers.bags import scan_stamps
    from disco_cli.search import rerank_depth

    if exclude_seconds is not None and exclude_frames is not None:
        raise DiscoError("give --exclude-seconds or --exclude-frames, not both")
    all_paths = scan_paths(sequence, scan_format, topic)
    poses_file = file_beside(sequence, poses)
    if poses_file is None and pose_topic is None:
        raise PoseFileError("no poses: give --poses FILE (or a folder with poses.txt)")
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, T = posed_scans(all_paths, poses_file, opts, warn, pose_topic)
    t, seconds = None, 30.0 if exclude_seconds is None else exclude_seconds
    if exclude_frames is None:
        times_file = file_beside(sequence, times, "times.txt")
        t = scan_stamps([str(p) for p in paths])  # scans in a bag carry their header stamp
        if times_file is not None or not np.isfinite(t).all():
            if times_file is None:
                raise PoseFileError("no times: give --times FILE or use --exclude-frames N")
            t = read_times(times_file)
            # One row per scan, or by frame number (the KITTI rule), for the scans with a pose.
            t = t[frame_rows(list(map(str, all_paths)), len(t), str(times_file))]
            kept = set(paths)
            t = t[[p in kept for p in all_paths]]
        if np.any(np.diff(t) < 0):
            raise PoseFileError(f"{times_file}: times go backwards")
    limit = exclusion_limits(len(paths), exclude_frames, t, seconds)
    model = load_model(model_name, device=device)
    apply_rerank(model, rerank)
    with _bar(len(paths)) as step:
        ev = loop_closure(paths, T, limit, model, radius, scan_format, step)
    run = {
        "protocol": "loop-closure",
        "model": model.name,
        "fingerprint": model.fingerprint,
        "rerank": rerank_depth(model),
        "sequence": " ".join(map(str, sequence)),
        "poses": str(poses_file) if pose_topic is None else pose_topic,
        "radius_m": radius,
        "exclusion": f"{exclude_frames} frames" if exclude_frames else f"{seconds:g} s",
        "num_scans": len(paths),
    }
    _report_and_print(ev, run, report, fmt)
