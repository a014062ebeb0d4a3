"""`disco correct`: the drift out of a sequence's odometry, by its loop closures.

The loops are `disco loops`' (a `LoopDetector` with verified relative poses), the pose
graph is `disco_cli.graph.pose_graph.PoseGraph` (GTSAM, the `[graph]` extra), and the
work is `disco_cli.graph.sequence.correct_sequence`, which a Python program calls too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

from disco_cli.commands.options import (
    ExcludeFramesOpt,
    MaxDistanceOpt,
    PosesFormatOpt,
    QuietOpt,
    ScanFormatOpt,
    SequenceArg,
    ThreadsOpt,
    TimesOpt,
    TopicOpt,
    opt,
    output_option,
)
from disco_cli.io.readers import list_scans
from disco_cli.runtime.console import fail, handle_errors, plural, say

PANEL_GRAPH = "Pose graph"


@handle_errors
def correct(
    sequence: SequenceArg,
    odometry: Annotated[
        Path,
        opt(
            "--odometry",
            help="The odometry: the LiDAR's pose per scan (KITTI 3x4 by frame, TUM by "
            "time, or any pose format disco reads; --poses-format).",
        ),
    ],
    output: Annotated[Path, output_option("The corrected trajectory, in the odometry's format.")],
    gt: Annotated[
        Optional[Path],
        opt("--gt", help="True poses of the scans: print ATE and RPE before and after."),
    ] = None,
    loops_out: Annotated[
        Optional[Path],
        opt("--loops-out", help="Also write the loops used: .g2o, .tum or .csv."),
    ] = None,
    kernel: Annotated[
        str,
        opt(
            "--kernel",
            panel=PANEL_GRAPH,
            help="Robust kernel of the loop edges: cauchy, huber, gnc or none.",
        ),
    ] = "cauchy",
    poses_format: PosesFormatOpt = None,
    exclude_frames: ExcludeFramesOpt = None,  # default 50
    max_distance: MaxDistanceOpt = None,
    times: TimesOpt = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    threads: ThreadsOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Correct a sequence's odometry by its loop closures: a pose graph of odometry and loop edges (GTSAM)."""  # noqa: E501
    from disco_cli.runtime.threads import set_threads  # deferred: not at start-up (--help)

    set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: numpy, the graph and the loop code load when the command runs (--help)
    import numpy as np

    from disco_cli.graph.pose_graph import KERNELS, import_gtsam
    from disco_cli.graph.sequence import correct_sequence, read_odometry, write_trajectory
    from disco_cli.io.loop_export import check_loop_file, write_loops
    from disco_cli.io.output_paths import check_output_file
    from disco_cli.io.poses import poses_for_scans
    from disco_cli.io.scan_inputs import sequence_times
    from disco_cli.query.loop_detector import LoopDetector
    from disco_cli.runtime.console import steps

    import_gtsam()  # before any work: one line naming the extra when it is missing
    if kernel not in KERNELS:
        raise fail(f"--kernel: unknown kernel {kernel!r}; use {', '.join(KERNELS)}")
    check_output_file(output, what="the corrected trajectory")
    if loops_out is not None:
        check_loop_file(loops_out)
    paths = [str(p) for p in list_scans(sequence, scan_format, topic)]
    stamps = sequence_times(sequence, paths, times)
    odo = read_odometry(paths, odometry, poses_format, stamps)
    truth = None
    if gt is not None:
        truth, _ = poses_for_scans(paths, gt, times=stamps)
        if not np.isfinite(truth).all():
            raise fail(f"{gt}: not every scan has a true pose; --gt needs one for each")
    # disco loops' own detector and defaults (confident loops, no pose); the loops that
    # go into the graph get their ICP pose after (graph/sequence.py), not its acceptance,
    # whose fitness bar refuses true loops on a changed campus: the kernel guards.
    detector = LoopDetector("default", exclude_frames=exclude_frames or 50, threshold=max_distance)
    with steps("loops", len(paths)) as advance:
        result = correct_sequence(
            paths, odo.poses, detector, times=stamps, scan_format=scan_format,
            threads=threads, on_progress=advance, kernel=kernel, on_pose_error=say,
        )  # fmt: skip
    c = result.correction
    written = write_trajectory(output, odo, c.poses)
    say(
        f"{sequence}: {plural(len(c.loops), 'loop')} in the graph ({result.found} found "
        f"among {plural(len(paths), 'scan')}), {len(c.down_weighted)} down-weighted "
        f"({kernel} kernel), heading drift {c.yaw_drift_deg_per_m:.4f} deg/m taken out"
    )
    for lp in c.down_weighted:
        say(
            f"  down-weighted: scan {lp.query} -> {lp.match}: residual {lp.residual:.1f} sigma "
            f"({lp.translation_m:.2f} m, {lp.rotation_deg:.1f} deg), weight {lp.weight:.3f}"
        )
    say(f"poses moved by {c.moved_m.mean():.3f} m on average, {c.moved_m.max():.3f} m at most")
    if truth is not None:
        from disco_cli.evaluation.trajectory import trajectory_errors  # deferred: --gt only

        b, a = trajectory_errors(odo.poses, truth), trajectory_errors(c.poses, truth)
        say(f"ATE {b.ate_m:.3f} m -> {a.ate_m:.3f} m (after a planar rigid alignment)")
        say(
            f"RPE {b.rpe_m:.4f} m, {b.rpe_deg:.4f} deg -> {a.rpe_m:.4f} m, {a.rpe_deg:.4f} deg "
            "(per scan)"
        )
    say(f"{output}: {plural(len(paths), 'pose')} written ({written})")
    if loops_out is not None:
        say(f"{loops_out}: {plural(write_loops(loops_out, result.loops), 'loop')} written")
