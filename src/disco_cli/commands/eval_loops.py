"""`disco eval-loops`: loop closure along one sequence against ground-truth poses.

The single-sequence protocol used on KITTI: every scan against the scans at least an
exclusion window before it. The work is `evaluation.runs.loop_closure`.
Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    MODEL_NAMES,
    PANEL_IN,
    PANEL_PROTOCOL,
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    MetricsFormatOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    QuietOpt,
    RadiusOpt,
    ReportOpt,
    RerankOpt,
    RerankWiderOpt,
    ScanFormatOpt,
    ThreadsOpt,
    TopicOpt,
    model_option,
    opt,
    pose_options,
    poses_option,
)
from disco_cli.errors import DiscoError
from disco_cli.query.query_policy import policy_for
from disco_cli.runtime.console import handle_errors, steps, warn


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
        Optional[Path], poses_option(PANEL_IN, help="Poses; default: the pose file in the folder.")
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
            help="Timestamps, one per scan; default: times.txt in the folder.",
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    model_name: Annotated[str, model_option(MODEL_NAMES, panel=PANEL_PROTOCOL)] = "default",
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
    threads: ThreadsOpt = None,
    rerank: RerankOpt = None,
    rerank_wider: RerankWiderOpt = None,
    report: ReportOpt = None,
    fmt: MetricsFormatOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Loop closure along one sequence: precision-recall, F1max, recall at 100% precision."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load
    # deferred: numpy and the evaluation code (~0.2 s) load when it runs, not for --help
    from disco_cli.evaluation.report import model_run, report_and_print
    from disco_cli.evaluation.runs import (
        check_loop_queries,
        exclusion_advice,
        exclusion_limits,
        loop_closure,
        posed_scans,
        posed_times,
    )
    from disco_cli.io.missed_poses import no_poses_error
    from disco_cli.io.output_paths import check_output_folder
    from disco_cli.io.scan_inputs import file_beside, scan_paths
    from disco_cli.model import load_model

    check_output_folder(report, what="the report")  # before the work it would lose
    if exclude_seconds is not None and exclude_frames is not None:
        raise DiscoError("give --exclude-seconds or --exclude-frames, not both")
    all_paths = scan_paths(sequence, scan_format, topic)
    poses_file = file_beside(sequence, poses)
    if poses_file is None and pose_topic is None:
        raise no_poses_error(all_paths, "poses", "--poses")
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, T = posed_scans(all_paths, poses_file, opts, warn, pose_topic)
    t, seconds = None, 30.0 if exclude_seconds is None else exclude_seconds
    if exclude_frames is None:
        t = posed_times(file_beside(sequence, times, "times.txt"), all_paths, paths)
    limit = exclusion_limits(len(paths), exclude_frames, t, seconds)
    advice = exclusion_advice(len(paths), exclude_frames, t, seconds)
    check_loop_queries(T, limit, radius, advice, warn)  # before the work: blank figures otherwise
    model = load_model(model_name, device=device)
    policy = policy_for(model, rerank=rerank, rerank_wider=rerank_wider)
    with steps("embedding", len(paths)) as step:
        ev = loop_closure(paths, T, limit, model, radius, scan_format, step, policy=policy)
    run = {
        "protocol": "loop-closure",
        **model_run(model, policy),
        "sequence": " ".join(map(str, sequence)),
        "poses": str(poses_file) if pose_topic is None else pose_topic,
        "radius_m": radius,
        "exclusion": f"{exclude_frames} frames" if exclude_frames else f"{seconds:g} s",
        "num_scans": len(paths),
    }
    report_and_print(ev, run, report, fmt)
