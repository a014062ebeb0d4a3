"""The two evaluation runs, from scans and poses to an `Evaluation` (the paper's dataset
settings that feed them are in `disco_cli/evaluation/protocols.py`).

- `multi_session`: the paper's protocol. Scans of one session are queried against a
  map database of another; the database's stored poses are the ground truth.
- `loop_closure`: the single-sequence protocol used on KITTI. Every scan against the
  scans at least an exclusion window before it.

Definitions of the metrics: docs/evaluation.md. `disco eval` and `disco eval-loops`
read the inputs, call these and print or write the report.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from disco_cli.embedding import batches
from disco_cli.errors import DatabaseError, DiscoError, PoseFileError
from disco_cli.evaluation.metrics import (
    loop_evaluation,
    one_percent_n,
    retrieval_evaluation,
    within_radius,
    wrap_deg,
)
from disco_cli.io.poses import ScanPoser, read_times, relative_yaw_deg, xy_yaw
from disco_cli.io.readers import read_scan
from disco_cli.io.readers.bags import bag_poses, scan_stamps
from disco_cli.io.scan_inputs import frame_rows
from disco_cli.maps.database import damaged_line
from disco_cli.query.loop_detector import LoopDetector

__all__ = [
    "multi_session",
    "loop_closure",
    "exclusion_limits",
    "posed_scans",
    "posed_times",
]


def posed_scans(
    paths: list[Any],
    poses_file: Any,
    pose_opts: dict,
    warn: Callable[[str], None],
    pose_topic: str | None = None,
) -> tuple[list[Any], np.ndarray]:
    """The scans that have a pose and their LiDAR poses: from a pose file
    (`disco_cli.io.poses.ScanPoser`), or for scans in bags from the bags' `pose_topic` by
    time. The others are named in one `warn` and left out of the evaluation."""
    if pose_topic is not None:
        source = pose_topic
        gap, extrinsic = pose_opts["max_time_gap"], pose_opts["extrinsic"]
        T, missing = bag_poses([str(p) for p in paths], pose_topic, gap, extrinsic)
        if missing:
            warn(
                f"{pose_topic}: {len(missing)} of {len(paths)} scans have no pose near their "
                f"stamp (e.g. {missing[0]}) and are left out of the evaluation"
            )
    else:
        source = poses_file
        T, report = ScanPoser(poses_file, **pose_opts).poses(paths)
        if report.warning():
            warn(report.warning() + " and left out of the evaluation")
    keep = np.isfinite(T[:, 0, 3])
    if not keep.any():
        raise PoseFileError(f"{source}: none of the {len(paths)} scans has a pose")
    return [p for p, k in zip(paths, keep) if k], T[keep]


def posed_times(times_file: Any, all_paths: list[Any], paths: list[Any]) -> np.ndarray:
    """The time (s) of each scan of `paths` (the scans of the sequence `all_paths` that
    have a pose): from `times_file` (one row per scan, or by frame number), else the
    header stamps of scans in bags. `PoseFileError` when there are none, or when they go
    backwards."""
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
    return t


def multi_session(
    paths: list[str],
    query_poses: np.ndarray,
    m: Any,
    radius: float = 3.0,
    topk: int = 25,
    scan_format: str | None = None,
    on_progress: Callable[[int], None] | None = None,
    source: str = "query poses",
    policy: Any = None,
) -> Any:
    """Recall@1..topk, Recall@1%, PR AUC, F1max (over the distance and over the
    confidence) and yaw error of `paths` (with their `[N, 4, 4]` `query_poses`) against
    the open `Map` `m`, queried as `disco query` queries it (`Map.query_files`, the
    stored signatures, the geometric check, the confidence) under the query stage's
    `policy` (None: the model's)."""
    db = m.database
    if len(query_poses) != len(paths):
        raise PoseFileError(f"{source}: {len(query_poses)} poses for {len(paths)} query scans")

    def refuse_damaged() -> None:  # scores count map rows by position: no holes allowed
        if db.damaged:
            line = damaged_line(db.damaged, db.path).replace("skipped", "found")
            raise DatabaseError(db.path, line)

    db_poses, _ = db.poses()
    refuse_damaged()
    if not np.isfinite(db_poses[:, :2]).all():
        raise DatabaseError(db.path, "some scans have no pose; build it with --poses")
    check_retrieval_queries(query_poses, db_poses, radius)  # before the work
    ids = db.ids()
    row_of = {int(i): r for r, i in enumerate(ids)}
    depth = max(topk, one_percent_n(len(ids)))
    matches = []
    for res in m.query_files(paths, topk=depth, scan_format=scan_format, policy=policy):
        if res.error is not None:
            raise res.error
        matches.append([_Scored(x, row_of[x.match_id]) for x in res.matches])
        if on_progress is not None:
            on_progress(1)
    refuse_damaged()
    return score_retrieval(matches, depth, topk, query_poses, db_poses, radius)


class _Scored:
    """A `Map.query` row as `score_retrieval` reads it: its row in the map's id order."""

    def __init__(self, match: Any, row: int):
        self.rank, self.row, self.distance = match.rank, row, match.distance
        self.yaw_deg = match.yaw_deg
        self.confidence = np.nan if match.confidence is None else match.confidence


def check_retrieval_queries(query_poses: np.ndarray, map_rows: np.ndarray, radius: float) -> None:
    """`DiscoError` when no query has a map scan within `radius` m: every figure would be
    blank (recall of nothing), so the evaluation is refused before it runs."""
    q = np.asarray(query_poses)[:, :2, 3]
    if len(q) and within_radius(q, map_rows[:, :2], radius).any():
        return
    raise DiscoError(
        f"0 of {len(q)} queries can be scored: none has a map scan within {radius:g} m; "
        "check that the queries and the map share one pose frame, or raise --radius"
    )


def exclusion_advice(
    n: int, exclude_frames: int | None, times: np.ndarray | None, seconds: float
) -> str:
    """Which option shortens eval-loops' exclusion window, with its value and the
    sequence's length, for `check_loop_queries`' message."""
    if exclude_frames is not None:
        return f"lower --exclude-frames (now {exclude_frames}; {n} scans)"
    span = float(times[-1] - times[0]) if times is not None and len(times) else 0.0
    return (
        f"lower --exclude-seconds (now {seconds:g} s; the sequence spans {span:.1f} s) "
        "or give --exclude-frames N"
    )


def check_loop_queries(
    poses: np.ndarray,
    limit: np.ndarray,
    radius: float,
    advice: str,
    warn: Callable[[str], None] | None = None,
) -> None:
    """`DiscoError` (with `advice`: which option to change) when no scan of the sequence
    can be scored, none having an earlier scan to search (`limit`). When queries there
    are but none has a true revisit within `radius` m (a drive that never returns),
    they still score precision (every detection is false), so `warn` says that
    recall, AUC and F1 stay blank. Checked before the work."""
    n = len(limit)
    queries = np.flatnonzero(np.asarray(limit) > 0)
    if len(queries) == 0:
        raise DiscoError(
            f"0 of {n} scans can be scored: none has a scan far enough before it to search "
            f"({advice})"
        )
    xy = np.asarray(poses)[:, :2, 3]
    near = within_radius(xy[queries], xy, radius)
    near &= np.arange(n)[None, :] < limit[queries][:, None]
    if not near.any() and warn is not None:
        warn(
            f"none of the {len(queries)} queries returns within {radius:g} m of a scan it "
            "may search: recall, AUC and F1 stay blank (raise --radius if it does return)"
        )


def score_retrieval(
    matches: list,
    depth: int,
    topk: int,
    query_poses: np.ndarray,
    map_rows: np.ndarray,
    radius: float,
) -> Any:
    """`retrieval_evaluation` of `match_queries`' results (searched `depth` deep): true
    matches within `radius` m in x, y of the `[N, 4, 4]` `query_poses`, with the map's
    scans as rows `[M, 4]` of x, y, z, yaw (radians); recall@N is cut at `topk`."""
    retrieved = np.full((len(matches), depth), -1, np.int64)
    distances = np.full((len(matches), depth), np.inf)
    yaw_est = np.full(len(matches), np.nan)
    conf = np.full(len(matches), np.nan)
    for i, found in enumerate(matches):
        for m in found:
            retrieved[i, m.rank - 1], distances[i, m.rank - 1] = m.row, m.distance
        if found:
            yaw_est[i] = found[0].yaw_deg
            conf[i] = getattr(found[0], "confidence", np.nan)
    qx, qy, qyaw = xy_yaw(query_poses)
    truth = within_radius(np.c_[qx, qy], map_rows[:, :2], radius)
    top1 = np.maximum(retrieved[:, 0], 0)
    # Ground-truth yaw of T_match^-1 T_query for planar poses: the heading difference.
    yaw_true = wrap_deg(np.degrees(qyaw - map_rows[top1, 3]))
    ev = retrieval_evaluation(retrieved, distances, truth, yaw_est, yaw_true, conf)
    # The search went deep enough for recall@1%; report recall@N up to the N asked for.
    ev.metrics["recall@N"] = ev.metrics["recall@N"][:topk]
    ev.metrics["topk"] = topk
    ev.recall_curve = ev.recall_curve[:topk]
    return ev


def exclusion_limits(
    n: int, exclude_frames: int | None, times: np.ndarray | None, seconds: float | None
) -> np.ndarray:
    """Scan i may match scans [0, limit[i]): at least `exclude_frames` frames back, or
    (times given) at least `seconds` s back."""
    if exclude_frames is not None:
        # Scan i searches scans 0 .. i - N.
        return np.maximum(np.arange(n) - exclude_frames + 1, 0)
    assert times is not None and seconds is not None
    return np.searchsorted(times, times - seconds, side="right")


def loop_closure(
    paths: list[str],
    poses: np.ndarray,
    limit: np.ndarray,
    model: Any,
    radius: float = 3.0,
    scan_format: str | None = None,
    on_progress: Callable[[int], None] | None = None,
    source: str = "poses",
    policy: Any = None,
) -> Any:
    """Precision-recall, F1max and recall at 100% precision of loop closure along one
    sequence (`[N, 4, 4]` poses; scan i searches scans [0, limit[i])), under the query
    stage's `policy` (None: the model's)."""
    n = len(paths)
    if len(poses) != n:
        raise PoseFileError(f"{source}: {len(poses)} poses for {n} scans")
    check_loop_queries(poses, limit, radius, "shorten the exclusion window")  # before the work
    sigs, feats = batches.embed_paths(paths, model, scan_format, on_progress=on_progress)
    # Every scan through the detector `disco loops` runs (its check and confidence),
    # every candidate kept: the scores are over all of them.
    det = LoopDetector(model, exclude_frames=None, min_confidence=None, policy=policy)
    queries = np.flatnonzero(limit > 0)
    found: dict[int, Any] = {}
    for i in range(n):

        def read(p: str = str(paths[i])) -> np.ndarray:
            return read_scan(p, scan_format)

        loops = det.add_embedded(sigs[i], feats[i], points=read, name=str(paths[i]), limit=limit[i])
        if loops:
            found[i] = loops[0]
    xy = poses[:, :2, 3]
    near = within_radius(xy[queries], xy, radius)
    near &= np.arange(n)[None, :] < limit[queries][:, None]
    has_true = near.any(axis=1)
    dist = np.full(len(queries), np.nan)
    conf = np.full(len(queries), np.nan)
    top = np.zeros(len(queries), np.int64)
    yaw_est = np.full(len(queries), np.nan)
    for k, i in enumerate(queries):
        if i in found:
            lp = found[i]
            dist[k], top[k], yaw_est[k] = lp.distance, lp.match_index, lp.yaw_deg
            conf[k] = np.nan if lp.confidence is None else lp.confidence
    correct = np.isfinite(dist) & near[np.arange(len(queries)), top]
    yaw_true = relative_yaw_deg(poses[top], poses[queries])
    return loop_evaluation(dist, correct, has_true, yaw_est, yaw_true, conf)
