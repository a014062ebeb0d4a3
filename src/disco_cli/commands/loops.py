"""`disco loops`: online loop-closure detection along one sequence.

Each scan is searched only against the scans at least N frames (or S seconds)
before it, as a robot would when it reaches that scan; the pairs closer than the
threshold are printed as loop candidates, with the yaw between them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_OUT,
    PANEL_RUN,
    DeviceOpt,
    OutputFormatOpt,
    RerankOpt,
    ScanFormatOpt,
    TopicOpt,
    WorkersOpt,
    apply_rerank,
)
from disco_cli.console import error, fail, handle_errors, progress, stderr, warn
from disco_cli.errors import DiscoError

if TYPE_CHECKING:
    import numpy as np

    from disco_cli.database import MatchRows

COLUMNS = ["query_index", "query", "match_index", "match", "distance", "yaw_deg"]
POSE_COLUMNS = ["dx", "dy", "dz", "fitness", "rmse", "accepted", "reason"]
PANEL_POSE = "Relative pose"
# Queries searched per block: their results are printed together.
_BLOCK = 64


@dataclass
class SequenceRows:
    """The `rows(ids)` of a database, for a sequence held in memory (ids = frame index)."""

    paths: list[str]
    features: np.ndarray

    def rows(self, ids: np.ndarray) -> MatchRows:
        import numpy as np

        from disco_cli.database import MatchRows

        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        return MatchRows(
            ids, [self.paths[i] for i in ids], np.full((len(ids), 4), np.nan), self.features[ids]
        )


class _Points:
    """Scan points by sequence index, the last few kept (pairs reuse recent scans)."""

    def __init__(self, paths: list[str], scan_format: str | None, size: int = 64):
        from collections import OrderedDict

        self.paths = paths
        self.scan_format = scan_format
        self.size = size
        self._cache: OrderedDict = OrderedDict()

    def get(self, i: int) -> np.ndarray:
        from disco_cli.readers import read_scan

        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        pts = read_scan(self.paths[i], self.scan_format)
        self._cache[i] = pts
        if len(self._cache) > self.size:
            self._cache.popitem(last=False)
        return pts


@handle_errors
def loops(
    sequence: Annotated[
        Path,
        typer.Argument(
            help="The sequence: a folder of scans (KITTI-style DIR/velodyne/ "
            "or a folder of scan files), or a ROS bag.",
            show_default=False,
        ),
    ],
    exclude_frames: Annotated[
        Optional[int],
        typer.Option(
            "--exclude-frames",
            min=1,
            help="Search only scans at least this many frames before the query. [default: 50]",
        ),
    ] = None,
    exclude_seconds: Annotated[
        Optional[float],
        typer.Option(
            "--exclude-seconds",
            min=0.0,
            help="Search only scans at least this many seconds before the query (times.txt).",
        ),
    ] = None,
    threshold: Annotated[
        Optional[float],
        typer.Option(
            "--threshold",
            "-t",
            min=0.0,
            help="Report pairs with a distance at most this (the `distance` column); default: all.",
        ),
    ] = None,
    topk: Annotated[
        int, typer.Option("--topk", "-k", min=1, max=1000, help="Candidates per query scan.")
    ] = 1,
    model: Annotated[
        str,
        typer.Option("--model", "-m", help="default, spectral, scancontext or a checkpoint path."),
    ] = "default",
    fmt: OutputFormatOpt = None,
    verify: Annotated[
        bool,
        typer.Option(
            "--verify",
            help="Estimate each pair's relative pose (phase "
            "correlation + ICP) and keep only the accepted ones.",
            rich_help_panel=PANEL_POSE,
        ),
    ] = False,
    verbose: Annotated[
        bool,
        typer.Option(
            "--verbose",
            "-v",
            help="Estimate each pair's relative pose and show "
            "it (dx, dy, dz, fitness, rmse, accepted, reason), rejected pairs "
            "included unless --verify.",
            rich_help_panel=PANEL_POSE,
        ),
    ] = False,
    output: Annotated[
        Optional[Path],
        typer.Option(
            "--output",
            "-o",
            help="Also write the loops with their "
            "relative poses: .g2o (EDGE_SE3:QUAT, accepted loops "
            "only), .tum or .csv.",
            rich_help_panel=PANEL_OUT,
        ),
    ] = None,
    times: Annotated[
        Optional[Path],
        typer.Option(
            "--times",
            help="Timestamps (s), one per scan; default: times.txt beside the scans.",
            rich_help_panel=PANEL_RUN,
        ),
    ] = None,
    db_path: Annotated[
        Optional[Path],
        typer.Option(
            "--db",
            "-d",
            help="Reuse the signatures of a database built "
            "from this sequence (same model); scans not in it are "
            "embedded.",
            rich_help_panel=PANEL_RUN,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    batch: Annotated[
        int,
        typer.Option(
            "--batch", min=1, max=4096, help="Scans per network batch.", rich_help_panel=PANEL_RUN
        ),
    ] = 32,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
) -> None:
    """Detect loop closures along one sequence of scans."""
    import numpy as np

    from disco_cli.console import RowWriter
    from disco_cli.database import Database, ModelInfo
    from disco_cli.model import load_model
    from disco_cli.pipeline import check_device, embed_stream, frame_rows, load_stream
    from disco_cli.poses import read_times
    from disco_cli.readers import list_scans
    from disco_cli.search import SignatureIndex, match_queries

    if exclude_frames is not None and exclude_seconds is not None:
        raise fail("give --exclude-frames or --exclude-seconds, not both")
    check_device(device)
    if output is not None:
        from disco_cli.loop_export import FORMATS

        if output.suffix.lower() not in FORMATS:
            raise fail(f"{output}: unknown loop file type; use {', '.join(FORMATS)}")
    with_pose = verify or verbose or output is not None
    fmt_name = scan_format.value if scan_format is not None else None
    paths = [str(p) for p in list_scans(sequence, fmt_name, topic)]
    n = len(paths)

    from disco_cli.readers.bags import scan_stamps

    # Scans in a bag carry their time (header stamp) in their names.
    bag_times = scan_stamps(paths) if times is None else None
    if bag_times is not None and not np.isfinite(bag_times).all():
        bag_times = None
    stamps = None
    all_times = bag_times
    times_file = times or (sequence / "times.txt" if sequence.is_dir() else None)
    if with_pose and times_file is not None and Path(times_file).is_file():
        t = read_times(times_file)
        all_times = t[frame_rows(paths, len(t), str(times_file))]
    if exclude_seconds is not None and bag_times is not None:
        stamps = bag_times
    elif exclude_seconds is not None:
        times_file = times or (sequence / "times.txt" if sequence.is_dir() else None)
        if times_file is None or not Path(times_file).is_file():
            raise fail(f"{sequence}: --exclude-seconds needs times.txt beside the scans or --times")
        t = read_times(times_file)
        stamps = t[frame_rows(paths, len(t), str(times_file))]

    net = load_model(model, device=device)
    apply_rerank(net, rerank)
    sigs: np.ndarray | None = None
    feats: np.ndarray | None = None
    known = np.zeros(n, dtype=bool)
    if db_path is not None:
        with Database.open(db_path) as db:
            db.check_model(ModelInfo.of(net))
            ids, stored = db.signatures()
            where = {p: k for k, p in enumerate(db.paths())}
            rows_in_db = [where.get(p, -1) for p in paths]
            have = [i for i, r in enumerate(rows_in_db) if r >= 0]
            if have:
                sigs = np.zeros((n, stored.shape[1]), np.float32)
                feats = np.zeros((n, *db.feature_shape), np.float32)
                sel = [rows_in_db[i] for i in have]
                sigs[have] = stored[sel]
                feats[have] = db.rows(ids[sel]).features
                known[have] = True
            del stored

    todo = [i for i in range(n) if not known[i]]
    if todo:
        loaded = load_stream(
            (paths[i] for i in todo),
            net.bev_config,
            workers=workers,
            prefetch=max(2 * batch, 4 * workers),
            scan_format=fmt_name,
        )
        try:
            with progress(transient=True) as bar:
                task = bar.add_task("embedding", total=len(todo), rate="")
                for chunk in embed_stream(loaded, net, batch):
                    for item in chunk.errors:
                        raise item.error  # type: ignore[misc]
                    if not chunk.items:
                        continue
                    if sigs is None:
                        sigs = np.zeros((n, chunk.signatures.shape[1]), np.float32)
                        feats = np.zeros((n, *chunk.features.shape[1:]), np.float32)
                    rows = [todo[it.index] for it in chunk.items]
                    sigs[rows] = chunk.signatures
                    feats[rows] = chunk.features
                    bar.advance(task, len(rows))
        finally:
            loaded.close()
    assert sigs is not None and feats is not None

    # Query i may match rows [0, limit[i]).
    if stamps is not None:
        if np.any(np.diff(stamps) < 0):
            warn(f"{sequence}: timestamps are not increasing; frames are taken in file order")
        # Scans at most t_i - S, and never the query itself or a later scan.
        limit = np.minimum(
            np.searchsorted(stamps, stamps - exclude_seconds, side="right"), np.arange(n)
        )
    else:
        gap = 50 if exclude_frames is None else exclude_frames
        limit = np.maximum(np.arange(n) - gap + 1, 0)

    index = SignatureIndex(sigs)
    store = SequenceRows(paths, feats)
    columns = COLUMNS + (POSE_COLUMNS if verbose else [])
    writer = RowWriter(columns, fmt, title=f"loops in {sequence}")
    frame_ids = np.arange(n)
    found_loops = []
    points = _Points(paths, fmt_name)
    pose_failures = 0
    for s in range(0, n, _BLOCK):
        block = np.arange(s, min(n, s + _BLOCK))
        block = block[limit[block] > 0]
        if len(block) == 0:
            continue
        found = match_queries(
            index,
            frame_ids,
            store,
            net,
            sigs[block],
            feats[block],
            topk,
            limit=limit[block],
            max_distance=threshold,
        )
        out = []
        for i, matches in zip(block, found):
            for m in matches:
                row = {
                    "query_index": int(i),
                    "query": paths[i],
                    "match_index": m.match_id,
                    "match": m.path,
                    "distance": m.distance,
                    "yaw_deg": m.yaw_deg,
                }
                if with_pose:
                    from disco_cli.loop_export import Loop
                    from disco_cli.relative_pose import estimate_relative_pose

                    try:
                        rp = estimate_relative_pose(
                            points.get(int(i)), points.get(m.match_id), m.yaw_deg
                        )
                    except DiscoError as exc:
                        # One unusable pair (e.g. a scan with no valid points) must not
                        # cost the loops already found: name it, go on, fail at the end.
                        error(f"{paths[i]} -> {m.path}: no relative pose ({exc})")
                        pose_failures += 1
                        continue
                    if verify and not rp.accepted:
                        continue
                    if verbose:
                        row.update(
                            dx=rp.dx,
                            dy=rp.dy,
                            dz=rp.dz,
                            fitness=rp.fitness,
                            rmse=rp.rmse,
                            accepted=rp.accepted,
                            reason=rp.reason,
                        )
                    t = all_times if all_times is not None else None
                    found_loops.append(
                        Loop(
                            int(i),
                            m.match_id,
                            paths[i],
                            m.path,
                            m.distance,
                            m.yaw_deg,
                            rp,
                            float(t[i]) if t is not None else float("nan"),
                            float(t[m.match_id]) if t is not None else float("nan"),
                        )
                    )
                out.append(row)
        if out:
            writer.write(out)
    if output is not None:
        from disco_cli.loop_export import write_loops

        keep = [lp for lp in found_loops if lp.pose.accepted or output.suffix.lower() != ".g2o"]
        write_loops(output, keep)
        stderr.print(f"{output}: {len(keep)} loops written")
    if pose_failures:
        raise typer.Exit(1)
