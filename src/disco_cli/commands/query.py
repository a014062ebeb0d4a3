"""`disco query`: the best matches of scans in a map database, with their yaw.

Queries stream: each scan's matches are written and flushed as soon as they are
ready, so `find . -name '*.bin' | disco query - --db map.db | head` works. A scan
that cannot be read gets one error line on stderr; the others go on, and the exit
status is 1 at the end. The work is `Map.query_files` (disco_cli/map.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    OutputFormatOpt,
    PosesFormatOpt,
    RerankOpt,
    ScanFormatOpt,
    ScanRootOpt,
    TopicOpt,
    WorkersOpt,
    apply_rerank,
    db_option,
    model_option,
    opt,
    pose_options,
    topk_option,
)
from disco_cli.console import error, fail, handle_errors, warn

COLUMNS = ["query", "rank", "match", "match_id", "distance", "yaw_deg"]
POSE_COLUMNS = ["roll_deg", "pitch_deg", "dx", "dy", "dz", "fitness", "accepted"]
PANEL_POSE = "Relative pose"
PANEL_FILTER = "Filters"


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
    exclude_radius: Annotated[
        Optional[float],
        opt(
            "--exclude-radius",
            min=0.0,
            panel=PANEL_FILTER,
            help="Drop matches whose stored "
            "pose is within this many metres (x, y) of the query's pose (needs --query-poses).",
        ),
    ] = None,
    query_poses: Annotated[
        Optional[Path],
        opt(
            "--query-poses",
            panel=PANEL_FILTER,
            help="Poses of the query scans (KITTI: row i for the i-th scan, or by frame number "
            "in the file name; other formats by time).",
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    max_distance: Annotated[
        Optional[float],
        opt(
            "--max-distance",
            min=0.0,
            panel=PANEL_FILTER,
            help="Drop matches with a distance above this (the `distance` column).",
        ),
    ] = None,
    pose: Annotated[
        bool,
        opt(
            "--pose",
            panel=PANEL_POSE,
            help="Also estimate the full relative pose of each match "
            "(phase correlation + ICP on the points): yaw_deg becomes the refined yaw, and "
            "roll_deg, pitch_deg, dx, dy, dz, fitness, accepted are added (JSON lines also carry "
            "the 4 x 4 T).",
        ),
    ] = False,
    verify: Annotated[
        bool,
        opt(
            "--verify",
            panel=PANEL_POSE,
            help="Keep only matches whose relative pose is accepted (implies --pose).",
        ),
    ] = False,
    model: Annotated[
        Optional[str],
        model_option(
            "The model; default: the one that built the database (needed for checkpoint paths)."
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    scan_root: ScanRootOpt = None,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
) -> None:
    """Find the places in a map database that scans were taken at, and the yaw to each."""
    from disco_cli.console import RowWriter
    from disco_cli.map import Map
    from disco_cli.pipeline import QueryPoses, stdin_paths
    from disco_cli.readers import is_bag, list_scans

    if exclude_radius is not None and query_poses is None:
        raise fail("--exclude-radius needs --query-poses")
    with_pose = pose or verify
    # A table is titled by its query, so its rows need not repeat the path.
    columns = COLUMNS + (POSE_COLUMNS if with_pose else [])
    writer = RowWriter(columns, fmt, table_omit=["query"])
    keys = columns + (["T"] if with_pose else [])  # JSON lines carry the whole T
    fmt_name = scan_format.value if scan_format is not None else None

    # A folder or a bag is expanded like build-db's (DIR/velodyne/, a folder of scans).
    def expand(a: str) -> list[str]:
        listed = a != "-" and (is_bag(a) or Path(a).is_dir())
        return [str(f) for f in list_scans(a, fmt_name, topic)] if listed else [a]

    given = [f for a in scans for f in expand(a)]
    paths = (p for s in given for p in (stdin_paths() if s == "-" else [s]))
    failed = 0
    with Map.open(db_path, model=model, device=device, scan_root=scan_root) as m:
        m.on_missing_scan = warn
        apply_rerank(m.model, rerank)
        exclude, poses_of = None, None
        if exclude_radius is not None:  # the query's own scan, and those near its pose
            opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
            # Scans in a bag go by the time in their names, scans from stdin one by one.
            known = None if "-" in given or any(map(is_bag, scans)) else given
            poses_of = QueryPoses(query_poses, opts, known, warn=error)
            exclude = lambda i, p: m.near(poses_of(i, p)[:2], exclude_radius, p)  # noqa: E731
        results = m.query_files(
            paths,
            topk=topk,
            pose=with_pose,
            exclude=exclude,
            max_distance=max_distance,
            workers=workers,
            scan_format=fmt_name,
        )
        for res in results:
            if res.error is not None:
                error(str(res.error))
                failed += 1
                continue
            rows = []
            for mt in res.matches:
                if with_pose and mt.T is None and mt.accepted is False:
                    error(f"{m.shown(mt.name)}: {mt.reason}")
                    failed += 1
                    continue
                if verify and not mt.accepted:
                    continue
                # A match whose scan is missing keeps its row, with the pose columns empty.
                row = {**mt.as_dict(), "query": res.name, "match": m.shown(mt.name)}
                rows.append({k: row.get(k) for k in keys})
            writer.write(rows, title=res.name)
    if poses_of is not None and poses_of.missing:
        error(f"{poses_of.missing} queries had no pose: only their own scan was excluded")
    if failed:
        raise typer.Exit(1)
