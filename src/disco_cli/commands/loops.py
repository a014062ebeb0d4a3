"""`disco loops`: online loop-closure detection along one sequence.

Each scan is searched only against the scans at least N frames (or S seconds) before
it, as a robot would when it reaches that scan; its best candidates are checked against
their geometry and only confident loops are reported (--all: every candidate). The work is
`LoopDetector.add_files` (disco_cli/query/loop_detector.py).
"""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    DEFAULT_MIN_CONFIDENCE,
    AllLoopsOpt,
    BatchOpt,
    DeviceOpt,
    ExcludeFramesOpt,
    ExcludeSecondsOpt,
    LoopFileOpt,
    LoopMinConfidenceOpt,
    MaxDistanceOpt,
    NoCheckOpt,
    OutputFormatOpt,
    QuietOpt,
    RerankOpt,
    RerankWiderOpt,
    ReuseDbOpt,
    ScanFormatOpt,
    ScanRootOpt,
    SequenceArg,
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
    sequence: SequenceArg,
    exclude_frames: ExcludeFramesOpt = None,  # default 50
    exclude_seconds: ExcludeSecondsOpt = None,
    max_distance: MaxDistanceOpt = None,
    min_confidence: LoopMinConfidenceOpt = None,
    all_candidates: AllLoopsOpt = False,
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
    no_check: NoCheckOpt = False,
    side_views: SideViewsOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Detect loop closures along one sequence of scans: each scan searches the scans at least 50 frames before it, its best 3 candidates are checked against their geometry, and only loops with a confidence of at least 0.85 are reported. query_index and match_index are positions in the sequence, from 0."""  # noqa: E501
    from disco_cli.runtime.threads import set_threads  # deferred: not at start-up (--help)

    set_threads(threads)  # first: torch and BLAS read it as they load
    # deferred: numpy and the map code (~0.2 s) load when the command runs, not for --help
    from disco_cli.io.loop_export import check_loop_file, write_loops
    from disco_cli.io.scan_inputs import window_times
    from disco_cli.maps.facade import Map, stored_embeddings
    from disco_cli.query.loop_detector import LoopDetector, loop_columns, loops_found
    from disco_cli.runtime.console import RowWriter, in_blocks, steps  # here: 150-line limit

    if exclude_frames is not None and exclude_seconds is not None:
        raise fail("give --exclude-frames or --exclude-seconds, not both")
    if all_candidates and min_confidence is not None:
        raise fail("give --all or --min-confidence, not both")
    bar = min_confidence if min_confidence is not None else DEFAULT_MIN_CONFIDENCE
    if output is not None:
        check_loop_file(output)
    with_pose = verify or verbose or output is not None
    paths = [str(p) for p in list_scans(sequence, scan_format, topic)]
    needs_times = with_pose or exclude_seconds is not None
    stamps = window_times(sequence, paths, times, exclude_seconds, warn) if needs_times else None
    pose_failures, found = [], []
    if model is None and db_path is not None:  # the map's own model, as every command
        with Map.open(db_path, device=device, scan_root=scan_root) as reused:
            model = reused.model
    detector = LoopDetector(
        model or "default",
        exclude_frames=None if exclude_seconds is not None else (exclude_frames or 50),
        exclude_seconds=exclude_seconds,
        threshold=max_distance,
        min_confidence=None if all_candidates else bar,
        verify=verify,
        pose=with_pose,
        topk=topk,
        rerank=rerank,
        device=device,
        on_pose_error=lambda msg: (error(msg), pose_failures.append(msg)),
        on_note=warn,
        side_views=side_views or 0.0,
    )
    detector.policy = policy_for(
        detector.model, detector.policy, rerank_wider=rerank_wider, check=not no_check
    )
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
    say(f"{sequence}: {loops_found(len(found), len(paths), detector.min_confidence)}")
    if output is not None:
        say(f"{output}: {plural(write_loops(output, found), 'loop')} written")
    if pose_failures:
        raise typer.Exit(1)
