"""`LoopDetector`: online loop closure, fed one scan at a time by a SLAM front end.

    detector = LoopDetector("default", exclude_frames=50)
    for points, T_world_sensor in odometry:                  # N x 3 / N x 4 arrays
        for loop in detector.add(points, pose=T_world_sensor):
            print(loop.query_index, loop.match_index, loop.T)  # T_match<-query

Each scan is searched only against the scans added at least an exclusion window
before it (frames, seconds, or metres travelled), as a robot would when it reaches
that scan, then added to the searchable set. The pairs within `threshold` are loop
candidates; with `verify` each gets its relative pose (phase correlation + ICP, see
`relative_pose.py`) and only accepted ones are returned. `disco loops` runs this
same class over a sequence's files, so both give the same loops.

Frames and units of `Loop`: as `Match` in `localize.py` (`T` is T_match<-query).
To verify later loops the detector keeps each scan's points (x, y, z as float32,
12 bytes a point) in memory; `add_files` reads them back from the files instead.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io import pipeline
from disco_cli.io.pipeline import array_points, embed_one, embed_side_views
from disco_cli.io.readers import read_scan
from disco_cli.maps.database import MatchRows
from disco_cli.maps.facade import _load_model
from disco_cli.maps.map_side_views import ViewIndex, side_offsets, side_view_bevs
from disco_cli.maps.signature_index import SignatureIndex
from disco_cli.query import relative_pose
from disco_cli.query.localize import PointCache, conf_or_none, pose_columns, pose_fields
from disco_cli.query.query_policy import policy_for
from disco_cli.query.search import match_queries

__all__ = ["Loop", "LoopDetector", "loop_columns"]


@dataclass(frozen=True, eq=False)  # eq would compare the arrays ambiguously
class Loop:
    """A loop closure: scan `query_index` was taken where scan `match_index` (an earlier
    one, 0-based in the order added) was. With a pose: `T` (4 x 4 T_match<-query,
    refined), `fitness`, `rmse`, `accepted`, `roll_deg`/`pitch_deg`, and `yaw_deg` is the
    refined yaw."""

    query_index: int
    match_index: int
    distance: float
    yaw_deg: float
    T: np.ndarray | None = field(default=None, repr=False)
    fitness: float | None = None
    rmse: float | None = None
    accepted: bool | None = None
    reason: str = ""  # why rejected; "" when accepted
    roll_deg: float | None = None
    pitch_deg: float | None = None
    query: str = ""  # the scans' names (their paths in `disco loops`)
    match: str = ""
    query_time: float = math.nan  # seconds, NaN when unknown
    match_time: float = math.nan
    yaw_conf: float | None = None  # in [0, 1] (localize.py); None: the model gives none

    def as_dict(self) -> dict[str, Any]:
        """The loop as the columns of `disco loops`, plus the pose columns and `T` (as
        nested lists) when it has a pose."""
        row = {"query_index": self.query_index, "query": self.query}
        row.update(match_index=self.match_index, match=self.match, distance=self.distance)
        return {**row, "yaw_deg": self.yaw_deg, "yaw_conf": self.yaw_conf, **pose_columns(self)}


def loop_columns(pose: bool, verbose: bool = False) -> tuple[list[str], list[str]]:
    """The columns of `disco loops` (with a `pose`, yaw_deg is the refined yaw and roll
    and pitch are added; `verbose` adds the rest of the pose and its scores), and the
    keys of its rows (JSON lines also carry `T`)."""
    columns = ["query_index", "query", "match_index", "match", "distance", "yaw_deg", "yaw_conf"]
    columns += ["roll_deg", "pitch_deg"] if pose else []
    columns += ["dx", "dy", "dz", "fitness", "rmse", "accepted", "reason"] if verbose else []
    return columns, columns + (["T"] if pose else [])


def _check_window(value: Any, name: str, minimum: float) -> Any:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= minimum:
        raise DiscoError(f"{name} must be a number >= {minimum:g}, not {value!r}")
    return value


class _Features:
    """The sequence's features, standing in for a database in `search.match_queries`
    (row = sequence index).

    Rows live in fixed blocks of `BLOCK` scans that are never copied or freed: a
    doubling array would, past a few thousand scans, hold both copies at once while
    growing (twice the features' memory), and freeing the old copy (tens of MB) makes
    glibc raise its mmap threshold, after which the heap keeps up to twice that much
    freed memory resident (the soak's step in docs/benchmarks.md)."""

    BLOCK = 256

    def __init__(self) -> None:
        self.blocks: list[np.ndarray] = []
        self.n = 0
        self.names: list[str] = []

    def append(self, features: np.ndarray, name: str) -> None:
        f = np.asarray(features, dtype=np.float32)
        if self.n == len(self.blocks) * self.BLOCK:
            self.blocks.append(np.empty((self.BLOCK, *f.shape), np.float32))
        self.blocks[-1][self.n % self.BLOCK] = f
        self.n += 1
        self.names.append(name)

    def nbytes(self) -> int:
        """Bytes of the rows in use."""
        return 0 if not self.blocks else self.n * self.blocks[0][0].nbytes

    def rows(self, ids: np.ndarray) -> Any:
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        feats = [self.blocks[i // self.BLOCK][i % self.BLOCK] for i in ids]
        shape = (0, *self.blocks[0].shape[1:]) if self.blocks else (0,)
        return MatchRows(
            ids,
            [self.names[i] for i in ids],
            np.full((len(ids), 4), np.nan),
            np.stack(feats) if feats else np.empty(shape, np.float32),
        )


class LoopDetector:
    """Online loop-closure detection; see the module docstring.

    `model`: a name (`default`, `spectral`, `scancontext`), a checkpoint path or a
    loaded model. Exclusion windows (every one given applies): `exclude_frames` (scan i
    searches scans 0 .. i - N; None: every earlier scan), `exclude_seconds` (scans at
    least S s older; every `add` needs `time`), `exclude_distance` (scans at least D m
    of travel back; every `add` needs `pose`). `threshold`: keep pairs with a distance
    at most this (None: all). `topk`: candidates per scan. `verify`: estimate each
    pair's relative pose and keep the accepted ones; `pose=True` without `verify`
    estimates it and keeps every pair. `on_pose_error(message)` hears of a pair whose
    pose cannot be estimated (that pair is left out); by default it is a warning.
    `side_views`: also search each earlier scan as seen from that many metres to its
    left and right (`map_side_views.py`), for revisits in another lane (a map's stored
    embeddings are then not reused: it holds no views of the sequence). `policy`: the
    query stage's `QueryPolicy` (default: the model's; `rerank` changes it); the
    `policy` attribute may be replaced before the first scan.
    """

    def __init__(
        self,
        model: Any = "default",
        *,
        exclude_frames: int | None = 50,
        exclude_seconds: float | None = None,
        exclude_distance: float | None = None,
        threshold: float | None = None,
        verify: bool = True,
        pose: bool | None = None,
        topk: int = 1,
        rerank: int | None = None,
        device: str = "cpu",
        pose_config: Any = None,
        on_pose_error: Callable[[str], None] | None = None,
        side_views: float = 0.0,
        policy: Any = None,
    ):
        if exclude_frames is not None and (
            isinstance(exclude_frames, bool) or int(exclude_frames) != exclude_frames
        ):
            raise DiscoError(f"exclude_frames must be an integer >= 1, not {exclude_frames!r}")
        self.exclude_frames = _check_window(exclude_frames, "exclude_frames", 1)
        self.exclude_seconds = _check_window(exclude_seconds, "exclude_seconds", 0.0)
        self.exclude_distance = _check_window(exclude_distance, "exclude_distance", 0.0)
        self.threshold = _check_window(threshold, "threshold", 0.0)
        if isinstance(topk, bool) or not isinstance(topk, int) or topk < 1:
            raise DiscoError(f"topk must be an integer >= 1, not {topk!r}")
        self.topk = topk
        try:
            self.side_offsets = side_offsets(side_views)
        except ValueError as exc:
            raise DiscoError(str(exc)) from None
        self.verify = bool(verify)
        self.estimate_pose = bool(verify or pose)
        self.pose_config = pose_config
        self._model = _load_model(model, device)
        # The query stage's settings (`QueryPolicy`; default: the model's).
        self.policy = policy_for(self._model, policy, rerank=rerank)
        self._on_pose_error = on_pose_error or (lambda msg: warnings.warn(msg, stacklevel=3))
        self._index: Any = None  # SignatureIndex, created with the first scan
        self._store = _Features()
        self._times = np.empty(0)
        self._travelled = np.empty(0)
        self._last_xyz: np.ndarray | None = None
        self._sources: dict[int, Any] = {}  # index -> points, or a function reading them
        self._points = PointCache(self._read_points, size=64)

    @property
    def model(self) -> Any:
        return self._model

    def __len__(self) -> int:
        return self._store.n

    # -- feeding -------------------------------------------------------------------

    def add(
        self, points: Any, *, pose: Any = None, time: float | None = None, name: str | None = None
    ) -> list[Loop]:
        """Add the next scan (an N x 3 or N x 4 array; `pose`: the sensor's 4 x 4 pose in
        the world, `time`: seconds) and return the loops it closes with earlier scans."""
        label = name or f"scan-{len(self)}"
        pts = array_points(points, label)
        sig, feat = embed_one(pts, self._model, label)
        sides = None
        if self.side_offsets:
            views = side_view_bevs(pts, self._model.bev_config, self.side_offsets)
            sides = embed_side_views([views], self._model)[0]
        keep = np.ascontiguousarray(pts[:, :3]) if self.estimate_pose else None
        return self.add_embedded(
            sig, feat, points=keep, pose=pose, time=time, name=label, side_signatures=sides
        )

    def add_embedded(
        self,
        signature: np.ndarray,
        features: np.ndarray,
        *,
        points: Any = None,
        pose: Any = None,
        time: float | None = None,
        name: str | None = None,
        side_signatures: np.ndarray | None = None,
    ) -> list[Loop]:
        """`add` for a scan embedded already (by `model.embed`); `points` is its point
        array or a function that reads it (needed when poses are estimated);
        `side_signatures` `[V, D]` its side views' (when the detector has side views)."""
        i = len(self)
        label = name or f"scan-{i}"
        t = self._time(time, label)
        travelled = self._travel(pose, label)
        sig = np.asarray(signature, dtype=np.float32).reshape(-1)
        if self.side_offsets and (
            side_signatures is None
            or np.shape(side_signatures) != (len(self.side_offsets), len(sig))
        ):
            raise DiscoError(f"{label}: this detector has side views; give their signatures")
        if self.estimate_pose:
            if points is None:
                raise DiscoError(f"{label}: no points to estimate the relative pose from")
            self._sources[i] = points
        limit = self._limit(i, t, travelled)
        loops: list[Loop] = []
        if limit > 0:
            found = match_queries(
                self._index,
                np.arange(i),
                self._store,
                self._model,
                sig[None],
                np.asarray(features, dtype=np.float32)[None],
                self.topk,
                self.policy,
                limit=[limit],
                max_distance=self.threshold,
            )[0]
            loops = [lp for m in found if (lp := self._loop(i, label, t, m)) is not None]
        # Only now is the scan searchable: never by itself.
        empty = np.empty((0, len(sig)), np.float32)
        if self._index is None and self.side_offsets:
            self._index = ViewIndex(empty, np.empty(0, np.int64), empty)
        elif self._index is None:
            self._index = SignatureIndex(empty)
        if self.side_offsets:
            self._index.append(sig[None], np.asarray(side_signatures)[None])
        else:
            self._index.append(sig[None])
        self._store.append(features, label)
        self._times = np.append(self._times, t)
        self._travelled = np.append(self._travelled, travelled)
        return loops

    def add_files(
        self,
        paths: list[str],
        *,
        times: np.ndarray | None = None,
        stored: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        batch: int = 32,
        threads: int | None = None,
        scan_format: str | None = None,
        on_progress: Callable[[int], None] | None = None,
    ) -> Iterator[list[Loop]]:
        """Feed scan files in order, yielding each one's loops as soon as it is
        embedded (in batches of `batch`, read and voxelized on `threads` threads; None:
        `disco_cli.get_threads()`).
        `times`: seconds per scan. `stored`: `Map.stored(paths)` of a map built from
        these files with the same model, whose signatures are used for the scans it
        holds. Points for poses are read back from the files when needed."""
        n = len(paths)
        if stored is not None and not self.side_offsets:  # a map stores no sequence's views
            known, sigs, feats = stored
        else:
            known, sigs, feats = np.zeros(n, bool), None, None
        fresh = self._embed_files(
            [paths[i] for i in range(n) if not known[i]], batch, threads, scan_format
        )
        for i, path in enumerate(paths):
            sides = None
            if known[i]:
                sig, feat = sigs[i], feats[i]  # type: ignore[index]
            else:
                sig, feat, sides = next(fresh)
            if on_progress is not None:
                on_progress(1)

            def read(p: str = path) -> np.ndarray:
                return read_scan(p, scan_format)

            yield self.add_embedded(
                sig,
                feat,
                points=read if self.estimate_pose else None,
                time=None if times is None else float(times[i]),
                name=path,
                side_signatures=sides,
            )

    def _embed_files(
        self, paths: list[str], batch: int, threads: int | None, scan_format: str | None
    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        if not paths:
            return
        with pipeline.embedded(  # looked up at each call: tests replace it
            iter(paths), self._model, batch, threads, scan_format, side_offsets=self.side_offsets
        ) as chunks:
            for chunk in chunks:
                for item in chunk.errors:
                    raise item.error  # type: ignore[misc]
                for j in range(len(chunk.items)):
                    sides = None if chunk.side_signatures is None else chunk.side_signatures[j]
                    yield chunk.signatures[j], chunk.features[j], sides

    # -- the pieces ----------------------------------------------------------------

    def _time(self, time: float | None, label: str) -> float:
        if time is None:
            if self.exclude_seconds is not None:
                raise DiscoError(f"{label}: exclude_seconds needs the time of every scan")
            return math.nan
        return float(time)

    def _travel(self, pose: Any, label: str) -> float:
        if pose is None:
            if self.exclude_distance is not None:
                raise DiscoError(f"{label}: exclude_distance needs the pose of every scan")
            return math.nan
        T = np.asarray(pose, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise DiscoError(f"{label}: pose must be a finite 4 x 4 matrix, got {T.shape}")
        xyz = T[:3, 3]
        before = self._travelled[-1] if len(self._travelled) else 0.0
        step = 0.0 if self._last_xyz is None else float(np.linalg.norm(xyz - self._last_xyz))
        self._last_xyz = xyz
        return float(before + step) if np.isfinite(before) else math.nan

    def _limit(self, i: int, t: float, travelled: float) -> int:
        """Scan i may match scans [0, limit)."""
        limit = i
        if self.exclude_frames is not None:
            limit = min(limit, max(i - int(self.exclude_frames) + 1, 0))
        if self.exclude_seconds is not None:
            found = np.searchsorted(self._times, t - self.exclude_seconds, side="right")
            limit = min(limit, int(found))
        if self.exclude_distance is not None:
            found = np.searchsorted(self._travelled, travelled - self.exclude_distance, "right")
            limit = min(limit, int(found))
        return limit

    def _read_points(self, i: int) -> np.ndarray:
        source = self._sources[i]
        return source() if callable(source) else source

    def _loop(self, i: int, label: str, t: float, m: Any) -> Loop | None:
        base = {
            "query_index": i,
            "match_index": m.match_id,
            "distance": m.distance,
            "yaw_deg": m.yaw_deg,
            "query": label,
            "match": m.path,
            "query_time": t,
            "match_time": float(self._times[m.match_id]),
            "yaw_conf": conf_or_none(m),
        }
        if not self.estimate_pose:
            return Loop(**base)
        try:
            rp = relative_pose.estimate_relative_pose(
                self._points.get(i), self._points.get(m.match_id), m.yaw_deg, self.pose_config
            )
        except DiscoError as exc:
            # One unusable pair (a scan with no valid points) must not cost the others.
            self._on_pose_error(f"{label} -> {m.path}: no relative pose ({exc})")
            return None
        if self.verify and not rp.accepted:
            return None
        return Loop(**{**base, **pose_fields(rp)})
