"""`disco query`: the best matches of scans in a map database, with their yaw.

Queries stream: each scan's matches are written and flushed as soon as they are
ready, so `find . -name '*.bin' | disco query - --db map.db | head` works. A scan
that cannot be read gets one error line on stderr; the others go on, and the exit
status is 1 at the end.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from disco_cli.commands.options import (
    PANEL_RUN,
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    OutputFormatOpt,
    PosesFormatOpt,
    RerankOpt,
    ScanFormatOpt,
    TopicOpt,
    WorkersOpt,
    apply_rerank,
    pose_options,
)
from disco_cli.console import error, fail, handle_errors

if TYPE_CHECKING:
    from disco_cli.database import Database

COLUMNS = ["query", "rank", "match", "match_id", "distance", "yaw_deg"]
POSE_COLUMNS = ["dx", "dy", "dz", "fitness", "accepted"]
PANEL_POSE = "Relative pose"
PANEL_FILTER = "Filters"


def open_for_model(db_path: Path, model: str | None, device: str) -> tuple[Database, Any]:
    """The database and the model it was built with (`model` overrides the stored name,
    e.g. a checkpoint path); refuses a model other than the database's."""
    from disco_cli.database import Database, ModelInfo
    from disco_cli.errors import DatabaseError
    from disco_cli.model import MODELS, load_model

    db = Database.open(db_path)
    name = model or db.meta.get("model_source") or db.model.name
    if model is None and name not in MODELS and not Path(name).is_file():
        raise DatabaseError(
            db_path, f"built with the checkpoint model '{db.model.name}'; pass --model PATH"
        )
    net = load_model(name, device=device)
    db.check_model(ModelInfo.of(net))
    return db, net


@handle_errors
def query(
    scans: Annotated[
        list[str],
        typer.Argument(
            help="Scan files, ROS bags (each of their scans; one as BAG#TOPIC@STAMP_NS), "
            "or - to read scan paths from stdin (one per line).",
            show_default=False,
        ),
    ],
    db_path: Annotated[
        Path, typer.Option("--db", "-d", help="The map database (from disco build-db).")
    ] = Path("map.db"),
    topk: Annotated[
        int, typer.Option("--topk", "-k", min=1, max=10000, help="Matches per query.")
    ] = 10,
    fmt: OutputFormatOpt = None,
    exclude_radius: Annotated[
        Optional[float],
        typer.Option(
            "--exclude-radius",
            min=0.0,
            help="Drop matches whose "
            "stored pose is within this many metres (x, y) of the "
            "query's pose (needs --query-poses).",
            rich_help_panel=PANEL_FILTER,
        ),
    ] = None,
    query_poses: Annotated[
        Optional[Path],
        typer.Option(
            "--query-poses",
            help="Poses of the query scans (KITTI: row i for the i-th scan, or by frame "
            "number in the file name; other formats by time).",
            rich_help_panel=PANEL_FILTER,
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    max_distance: Annotated[
        Optional[float],
        typer.Option(
            "--max-distance",
            min=0.0,
            help="Drop matches with a distance above this (the `distance` column).",
            rich_help_panel=PANEL_FILTER,
        ),
    ] = None,
    pose: Annotated[
        bool,
        typer.Option(
            "--pose",
            help="Also estimate the full relative pose of each match "
            "(phase correlation + ICP on the points): adds dx, dy, dz, fitness, "
            "accepted.",
            rich_help_panel=PANEL_POSE,
        ),
    ] = False,
    verify: Annotated[
        bool,
        typer.Option(
            "--verify",
            help="Keep only matches whose relative pose is accepted (implies --pose).",
            rich_help_panel=PANEL_POSE,
        ),
    ] = False,
    model: Annotated[
        Optional[str],
        typer.Option(
            "--model",
            "-m",
            help="The model; default: the one that "
            "built the database (needed for checkpoint paths).",
            rich_help_panel=PANEL_RUN,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
) -> None:
    """Find the places in a map database that scans were taken at, and the yaw to each."""
    import numpy as np

    from disco_cli.console import RowWriter
    from disco_cli.errors import DiscoError, PoseFileError
    from disco_cli.pipeline import check_device, embed_stream, load_stream, pose_rows, stdin_paths
    from disco_cli.readers import is_bag, list_scans
    from disco_cli.search import SignatureIndex, match_queries

    if exclude_radius is not None and query_poses is None:
        raise fail("--exclude-radius needs --query-poses")
    check_device(device)
    db, net = open_for_model(db_path, model, device)
    apply_rerank(net, rerank)
    ids, sigs = db.signatures()
    index = SignatureIndex(sigs)
    db_xy = None
    poser = None
    if exclude_radius is not None:
        from disco_cli.poses import ScanPoser

        db_xy = db.poses()[0][:, :2]
        db_files = np.array([str(Path(p).resolve()) for p in db.paths()])
        poser = ScanPoser(query_poses, **pose_options(poses_format, calib, extrinsic, max_time_gap))
        # With the query scans on the command line, KITTI's "row i for scan i" applies
        # when their count is the file's; from stdin each scan goes by its frame number
        # (a scan in a bag by the time in its name).
        q_rows = None
        if "-" not in scans and not any(map(is_bag, scans)):
            T, report = poser.poses(list(scans))
            q_rows = pose_rows(T)
            if report.warning():
                error(report.warning())

    def paths():
        for s in scans:
            if s == "-":
                yield from stdin_paths()
            elif is_bag(s):
                yield from map(str, list_scans(s, topic=topic))
            else:
                yield s

    with_pose = pose or verify
    # A table is titled by its query, so its rows need not repeat the path.
    writer = RowWriter(COLUMNS + (POSE_COLUMNS if with_pose else []), fmt, table_omit=["query"])
    failed = 0
    no_pose = 0  # queries without a pose: only their own scan is excluded
    match_points = PointCache()
    loaded = load_stream(
        paths(),
        net.bev_config,
        workers=workers,
        prefetch=2 * workers,
        scan_format=scan_format.value if scan_format is not None else None,
        keep_points=with_pose,
    )
    try:
        for chunk in embed_stream(loaded, net, batch=1):
            for item in chunk.errors:
                error(str(item.error))
                failed += 1
            for j, item in enumerate(chunk.items):
                exclude = None
                try:
                    if poser is not None:
                        if q_rows is not None:
                            row = q_rows[item.index]
                        else:
                            T, report = poser.poses([item.path])
                            row = pose_rows(T)[0]
                            if report.missing and not no_pose:
                                error(report.warning())
                        # The query's own scan is excluded by its path; the others by
                        # distance (unknown poses, NaN, are never within the radius).
                        exclude = db_files == str(Path(item.path).resolve())
                        if np.isfinite(row[:2]).all():
                            d = np.hypot(db_xy[:, 0] - row[0], db_xy[:, 1] - row[1])
                            exclude |= d <= exclude_radius
                        else:
                            no_pose += 1
                except PoseFileError as exc:
                    error(str(exc))
                    failed += 1
                    continue
                try:
                    matches = match_queries(
                        index,
                        ids,
                        db,
                        net,
                        chunk.signatures[j : j + 1],
                        chunk.features[j : j + 1],
                        topk,
                        exclude=exclude,
                        max_distance=max_distance,
                    )[0]
                except DiscoError as exc:
                    error(str(exc))
                    failed += 1
                    continue
                rows = [
                    {
                        "query": item.path,
                        "rank": m.rank,
                        "match": m.path,
                        "match_id": m.match_id,
                        "distance": m.distance,
                        "yaw_deg": m.yaw_deg,
                    }
                    for m in matches
                ]
                if with_pose:
                    from disco_cli.relative_pose import estimate_relative_pose

                    kept = []
                    for row in rows:
                        try:
                            rp = estimate_relative_pose(
                                item.points, match_points.get(row["match"]), row["yaw_deg"]
                            )
                        except DiscoError as exc:
                            error(f"{row['match']}: no relative pose ({exc})")
                            failed += 1
                            continue
                        row.update(
                            dx=rp.dx, dy=rp.dy, dz=rp.dz, fitness=rp.fitness, accepted=rp.accepted
                        )
                        if rp.accepted or not verify:
                            kept.append(row)
                    rows = kept
                    item.points = None
                writer.write(rows, title=item.path)
    finally:
        loaded.close()
        db.close()
    if no_pose:
        error(f"{no_pose} queries had no pose: only their own scan was excluded")
    if failed:
        raise typer.Exit(1)


class PointCache:
    """The points of the last few match scans read (a query's matches often repeat)."""

    def __init__(self, size: int = 32):
        from collections import OrderedDict

        self.size = size
        self._cache: OrderedDict = OrderedDict()

    def get(self, path: str) -> Any:
        from disco_cli.readers import read_scan

        if path in self._cache:
            self._cache.move_to_end(path)
            return self._cache[path]
        points = read_scan(path)
        self._cache[path] = points
        if len(self._cache) > self.size:
            self._cache.popitem(last=False)
        return points
