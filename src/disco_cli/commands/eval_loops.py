"""`disco eval-loops`: loop closure along one sequence against ground-truth poses.

The single-sequence protocol used on KITTI: every scan against the scans at least an
exclusion window before it. The work is `evaluation.protocols.loop_closure`.
Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.evaluate import (
    PANEL_INPUT,
    PANEL_PROTOCOL,
    CalibOpt,
    FormatOpt,
    RadiusOpt,
    ReportOpt,
    _bar,
    _report_and_print,
)
from disco_cli.commands.options import (
    DeviceOpt,
    RerankOpt,
    ScanFormatOpt,
    apply_rerank,
    model_option,
    opt,
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
        opt("--poses", help="KITTI poses; default: poses.txt in the folder.", panel=PANEL_INPUT),
    ] = None,
    calib: CalibOpt = None,
    times: Annotated[
        Optional[Path],
        opt(
            "--times",
            panel=PANEL_INPUT,
            help="Timestamps, one per scan; default: times.txt in the folder.",
        ),
    ] = None,  # fmt: skip
    scan_format: ScanFormatOpt = None,
    model_name: Annotated[
        str,
        model_option("default, spectral, scancontext or a checkpoint path.", panel=PANEL_PROTOCOL),
    ] = "default",  # fmt: skip
    radius: RadiusOpt = 3.0,
    exclude_seconds: Annotated[
        Optional[float],
        opt(
            "--exclude-seconds",
            min=0.0,
            panel=PANEL_PROTOCOL,
            help="Search only scans at least this long before (default 30; needs times).",
        ),
    ] = None,  # fmt: skip
    exclude_frames: Annotated[
        Optional[int],
        opt(
            "--exclude-frames",
            min=1,
            panel=PANEL_PROTOCOL,
            help="Search only scans at least N frames before.",
        ),
    ] = None,  # fmt: skip
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    report: ReportOpt = None,
    fmt: FormatOpt = None,
) -> None:
    """Loop closure along one sequence: precision-recall, F1max, recall at 100% precision."""
    import numpy as np

    from disco_cli.errors import DiscoError, PoseFileError
    from disco_cli.evaluation.protocols import exclusion_limits, loop_closure
    from disco_cli.model import load_model
    from disco_cli.pipeline import file_beside, scan_paths
    from disco_cli.poses import read_kitti_poses, read_times
    from disco_cli.search import rerank_depth

    if exclude_seconds is not None and exclude_frames is not None:
        raise DiscoError("give --exclude-seconds or --exclude-frames, not both")
    paths = scan_paths(sequence, scan_format)
    poses_file = file_beside(sequence, poses, "poses.txt")
    if poses_file is None:
        raise PoseFileError("no poses: give --poses FILE (or a folder with poses.txt)")
    T = read_kitti_poses(poses_file, calib)
    if len(T) != len(paths):
        raise PoseFileError(f"{poses_file}: {len(T)} poses for {len(paths)} scans")
    t, seconds = None, 30.0 if exclude_seconds is None else exclude_seconds
    if exclude_frames is None:
        times_file = file_beside(sequence, times, "times.txt")
        if times_file is None:
            raise PoseFileError("no times: give --times FILE or use --exclude-frames N")
        t = read_times(times_file)
        if len(t) != len(paths):
            raise PoseFileError(f"{times_file}: {len(t)} times for {len(paths)} scans")
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
        "poses": str(poses_file),
        "radius_m": radius,
        "exclusion": f"{exclude_frames} frames" if exclude_frames else f"{seconds:g} s",
        "num_scans": len(paths),
    }
    _report_and_print(ev, run, report, fmt)
