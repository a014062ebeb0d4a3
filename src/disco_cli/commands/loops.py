"""`disco loops`: online loop-closure detection along one sequence.

Each scan is searched only against the scans at least N frames (or S seconds) before
it, as a robot would when it reaches that scan. The work is `LoopDetector.add_files`
(disco_cli/query/loop_detector.py), the class a Python program feeds scan by scan.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    BatchOpt,
    DeviceOpt,
    ExcludeFramesOpt,
    ExcludeSecondsOpt,
    LoopFileOpt,
    MaxDistanceOpt,
    OutputFormatOpt,
    QuietOpt,
    RerankOpt,
    RerankWiderOpt,
    ReuseDbOpt,
    ScanFormatOpt,
    ScanRootOpt,
    SideViewsOpt,
    ThreadsOpt,
    TimesOpt,
    TopicOpt,
    VerboseLoopsOpt,
    VerifyLoopsOpt,
    model_option,
    topk_option,
)
from disco_cli.io.readers import list_scans
from disco_cli.query.query_policy import policy_for
from disco_cli.runtime.console import error, fail, handle_errors, plural, say, warn

MODEL_OF_SEQUENCE = "default, spectral, scancontext or a checkpoint; default: the --db map's."


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
    max_distance: MaxDistanceOpt = None,
    topk: Annotated[int, topk_option("Candidates per query scan.")] = 1,
    model: Annotated[Optional[str], model_option(MODEL_OF_SEQUENCE, panel=None)] = None,
    fmt: OutputFormatOpt = None,
    verify: VerifyLoopsOpt = False,
    verbose: VerboseLoopsOpt = False,
    output: LoopFileOpt = None,
    times: TimesOpt = None,
    db_path: ReuseDbOpt = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    scan_root: ScanRootOpt = None,
    batch: BatchOpt = 32,
    threads: ThreadsOpt = None,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    rerank_wider: RerankWiderOpt = None,
    side_views: SideViewsOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Detect loop closures along one sequence of scans (by default each scan searches the scans at least 50 frames before it).

    query_index and match_index are positions in the sequence, from 0 (query's match_id: from 1).
    """  # noqa: E501
    from disco_cli.runtime.threads import set_threads  # deferred: not at start-up (--help)

    set_threads(threads)  # first: torch and BLAS read it as they load

    import numpy as np  # deferred: with the map code below (~0.2 s), not for --help

    from disco_cli.io.loop_export import check_loop_file, write_loops
    from disco_cli.io.pipeline import sequence_times
    from disco_cli.maps.facade import Map, stored_embeddings
    from disco_cli.query.loop_detector import LoopDetector, loop_columns
    from disco_cli.runtime.console import RowWriter, in_blocks, steps  # here: 150-line limit

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
    pose_failures, found = [], []
    if model is None and db_path is not None:  # the map's own model, as every command
        with Map.open(db_path, device=device, scan_root=scan_root) as reused:
            model = reused.model
    detector = LoopDetector(
        model or "default",
        exclude_frames=None if exclude_seconds is not None else (exclude_frames or 50),
        exclude_seconds=exclude_seconds,
        threshold=max_distance,
        verify=verify,
        pose=with_pose,
        topk=topk,
        rerank=rerank,
        device=device,
        on_pose_error=lambda msg: (error(msg), pose_failures.append(msg)),
        side_views=side_views or 0.0,
    )
    detector.policy = policy_for(detector.model, detector.policy, rerank_wider=rerank_wider)
    columns, keys = loop_columns(with_pose, verbose)
    writer = RowWriter(columns, fmt, title=f"loops in {sequence}")
    reuse = None
    if db_path is not None and side_views:
        warn(f"{db_path}: not reused with --side-views (a map holds no views of the sequence)")
    elif db_path is not None:
        reuse = stored_embeddings(db_path, paths, detector.model, scan_root=scan_root, warn=warn)
    with steps("loops", len(paths)) as advance:
        stream = detector.add_files(
            paths,
            times=stamps,
            stored=reuse,
            batch=batch,
            threads=threads,
            scan_format=scan_format,
            on_progress=advance,
        )
        for block in in_blocks(stream, 64):  # the loops of 64 query scans in one table
            found += block
            writer.write([{k: lp.as_dict()[k] for k in keys} for lp in block])
    if not found:
        writer.write([])  # the header (an empty table), so that "no loop" reads as an answer
    say(f"{sequence}: {plural(len(found), 'loop candidate')} among {plural(len(paths), 'scan')}")
    if output is not None:
        say(f"{output}: {plural(write_loops(output, found), 'loop')} written")
    if pose_failures:
        raise typer.Exit(1)
