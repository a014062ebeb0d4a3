"""`disco query`: the best matches of scans in a map database, with their yaw.

Queries stream: each scan's matches are written and flushed as soon as they are
ready, so `find . -name '*.bin' | disco query - --db map.db | head` works. A scan
that cannot be read gets one error line on stderr; the others go on, and the exit
status is 1 at the end. The work is `Map.query_files` (disco_cli/maps/facade.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    MODEL_OF_MAP,
    PANEL_FILTER,
    CalibOpt,
    DeviceOpt,
    ExcludeRadiusOpt,
    ExtrinsicOpt,
    IndexOpt,
    MaxDistanceOpt,
    MaxTimeGapOpt,
    MinConfidenceOpt,
    NoCheckOpt,
    OutputFormatOpt,
    PoseOpt,
    PosesFormatOpt,
    RefineYawOpt,
    RerankOpt,
    RerankWiderOpt,
    ScanFormatOpt,
    ScanRootOpt,
    SnapRadiusOpt,
    ThreadsOpt,
    TopicOpt,
    VerifyMatchesOpt,
    db_option,
    model_option,
    pose_options,
    poses_option,
    topk_option,
)
from disco_cli.query.query_policy import policy_for
from disco_cli.runtime.columns import POSE_COLUMNS
from disco_cli.runtime.columns import RESULT_COLUMNS as COLUMNS
from disco_cli.runtime.console import RowWriter, error, fail, handle_errors, note, warn


@handle_errors
def query(
    scans: Annotated[
        list[str],
        typer.Argument(
            help="Scan files, folders of scans (as for build-db), ROS bags (each of their "
            "scans; one as BAG#TOPIC@STAMP_NS), or - to read scan paths from stdin (one per line).",
            show_default=False,
        ),
    ],
    db_path: Annotated[Path, db_option("The map database (from disco build-db).")] = Path("map.db"),
    topk: Annotated[int, topk_option("Matches per query.")] = 10,
    fmt: OutputFormatOpt = None,
    exclude_radius: ExcludeRadiusOpt = None,
    query_poses: Annotated[
        Optional[Path],
        poses_option(
            PANEL_FILTER,
            help="Poses of the query scans, for --exclude-radius (KITTI: row i for the i-th "
            "scan, or by frame number in the file name; other formats by time).",
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    max_distance: MaxDistanceOpt = None,
    min_confidence: MinConfidenceOpt = None,
    pose: PoseOpt = False,
    verify: VerifyMatchesOpt = False,
    model: Annotated[Optional[str], model_option(MODEL_OF_MAP)] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    scan_root: ScanRootOpt = None,
    threads: ThreadsOpt = None,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    rerank_wider: RerankWiderOpt = None,
    refine_yaw: RefineYawOpt = None,
    snap_radius: SnapRadiusOpt = None,
    no_check: NoCheckOpt = False,
    index: IndexOpt = "auto",
) -> None:
    """Find the places in a map database that scans were taken at, and the yaw to each.

    match_id is the scan's id in the map: 1 for the first scan stored, in the order
    build-db stored them (info and --repair count the same way). disco loops instead
    numbers a sequence's scans by position, from 0.
    """
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load

    # deferred: numpy and the map code (~0.2 s) load when the command runs, not for --help
    from disco_cli.io.scan_inputs import QueryPoses, query_paths
    from disco_cli.maps.facade import Map

    if exclude_radius is not None and query_poses is None:
        raise fail("--exclude-radius needs --poses")
    with_pose = pose or verify
    # A table is titled by its query, so its rows need not repeat the path.
    columns = COLUMNS + (POSE_COLUMNS if with_pose else [])
    writer = RowWriter(columns, fmt, table_omit=["query"])
    keys = columns + (["T"] if with_pose else [])  # JSON lines carry the whole T
    fmt_name = scan_format.value if scan_format is not None else None
    paths, known = query_paths(scans, fmt_name, topic)
    failed, poses_of, exclude = 0, None, None
    with Map.open(db_path, model=model, device=device, scan_root=scan_root, index=index) as m:
        m.on_missing_scan, m.on_index_note, m.on_damaged = warn, note, warn
        settings = dict(rerank=rerank, rerank_wider=rerank_wider, snap_radius=snap_radius)
        policy = policy_for(m.model, **settings, refine_yaw=refine_yaw, check=not no_check)
        if exclude_radius is not None:  # the query's own scan, and those near its pose
            opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
            poses_of = QueryPoses(query_poses, opts, known, warn=error)
            exclude = poses_of.exclusion(m, exclude_radius)
        results = m.query_files(
            paths,
            topk=topk,
            pose=with_pose,
            exclude=exclude,
            max_distance=max_distance,
            min_confidence=min_confidence,
            threads=threads,
            scan_format=fmt_name,
            policy=policy,
        )
        for res in results:
            rows, errors = res.rows(m.shown, keys, verify=verify)
            for msg in errors:
                error(msg)
            failed += len(errors)
            if res.error is None:
                writer.write(rows, title=res.name)
    if poses_of is not None and poses_of.missing:
        error(f"{poses_of.missing} queries had no pose: only their own scan was excluded")
    if failed:
        raise typer.Exit(1)
