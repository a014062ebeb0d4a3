"""`LoopDetector`: online loop closure, fed one scan at a time by a SLAM front end.

    detector = LoopDetector("default", exclude_frames=50)
    for points, T_world_sensor in odometry:                  # N x 3 / N x 4 arrays
        for loop in detector.add(points, pose=T_world_sensor):
            print(loop.query_index, loop.match_index, loop.T)  # T_match<-query

Each scan is searched only against the scans added at least an exclusion window
before it (frames, seconds, or metres travelled), as a robot would when it reaches
that scan, then added to the searchable set. Its best few candidates are checked
geometrically (`verification.py`: the layout check of `relative_pose.py`) and
each loop carries a `confidence`, the estimated probability that it is a true revisit
(`confidence.py`); by default only loops at or above `LOOP_MIN_CONFIDENCE` are
returned, chosen on the selection worlds for a precision of 99.5 % or more
(docs/confidence.md). `min_confidence=None` returns every candidate. `disco loops`
runs this same class over a sequence's files, so both give the same loops.

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

from disco_cli.embedding import batches
from disco_cli.embedding.batches import embed_one, embed_side_views
from disco_cli.embedding.load import array_points, side_view_bevs
from disco_cli.errors import DiscoError
from disco_cli.io.readers import read_scan
from disco_cli.maps.database import MatchRows
from disco_cli.maps.facade import _load_model
from disco_cli.maps.map_side_views import ViewIndex, side_offsets
from disco_cli.maps.signature_index import SignatureIndex
from disco_cli.query.confidence import calibrated
from disco_cli.query.localize import Match, PointCache, as_match, pose_columns
from disco_cli.query.query_policy import policy_for
from disco_cli.query.search import match_queries
from disco_cli.query.verification import check_candidates, check_row

__all__ = ["Loop", "LoopDetector", "loop_columns", "loops_found", "LOOP_MIN_CONFIDENCE"]

# The confidence a loop needs by default: the lowest bar, in steps of 0.05, at which the
# default loops on none of the nine selection worlds' joined sequences (8621-8623, every
# family) held a false loop; precision 100 % on each, where 99.5 % was asked. Wrong
# places (28-239 m off) reached 0.80 at most there (docs/confidence.md,
# `benchmarks/calibrate_confidence.py loops`).
LOOP_MIN_CONFIDENCE = 0.85


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
    # The estimated probability that the loop is true (confidence.py); None: the model
    # has no calibration.
    confidence: float | None = None

    def as_dict(self) -> dict[str, Any]:
        """The loop as the columns of `disco loops`, plus the pose columns and `T` (as
        nested lists) when it has a pose."""
        row = {"query_index": self.query_index, "query": self.query}
        row.update(match_index=self.match_index, match=self.match, distance=self.distance)
        row.update(confidence=self.confidence, yaw_deg=self.yaw_deg, yaw_conf=self.yaw_conf)
        return {**row, **pose_columns(self)}


def loop_columns(pose: bool, verbose: bool = False) -> tuple[list[str], list[str]]:
    """The columns of `disco loops` (with a `pose`, yaw_deg is the refined yaw and roll
    and pitch are added; `verbose` adds the rest of the pose and its scores), and the
    keys of its rows (JSON lines also carry `T`)."""
    columns = ["query_index", "query", "match_index", "match", "distance", "confidence"]
    columns += ["yaw_deg", "yaw_conf"]
    columns += ["roll_deg", "pitch_deg"] if pose else []
    columns += ["dx", "dy", "dz", "fitness", "rmse", "accepted", "reason"] if verbose else []
    return columns, columns + (["T"] if pose else [])


def loops_found(loops: int, scans: int, bar: float | None) -> str:
    """`6 loops with confidence >= 0.9 among 26 scans` (`bar` None: every candidate)."""
    s = "" if loops == 1 else "s"
    kept = (
        f"{loops} loop candidate{s}"
        if bar is None
        else f"{loops} loop{s} with confidence >= {bar:g}"
    )
    return f"{kept} among {scans} scan{'' if scans == 1 else 's'}"


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
        found = ids, [self.names[i] for i in ids], np.full((len(ids), 4), np.nan)
        if len(ids) == 0:
            shape = (0, *self.blocks[0].shape[1:]) if self.blocks else (0,)
            return MatchRows(*found, np.empty(shape, np.float32))
        # Each row's own place in its block, as `Database.rows` hands out its cache's:
        # read where it lies, and nobody writes into the store through it.
        feats = []
        for i in ids:
            row = self.blocks[i // self.BLOCK][i % self.BLOCK]
            row.flags.writeable = False  # this view only; the block stays writable
            feats.append(row)
        return MatchRows(*found, feature_rows=feats)


class LoopDetector:
    """Online loop-closure detection; see the module docstring.

    `model`: a name (`default`, `spectral`, `scancontext`), a checkpoint path or a
    loaded model. Exclusion windows (every one given applies): `exclude_frames` (scan i
    searches scans 0 .. i - N; None: every earlier scan), `exclude_seconds` (scans at
    least S s older; every `add` needs `time`), `exclude_distance` (scans at least D m
    of travel back; every `add` needs `pose`). `threshold`: keep pairs with a distance
    at most this (None: all). `topk`: candidates per scan. `min_confidence`: keep the
    loops whose confidence is at least this (default `LOOP_MIN_CONFIDENCE`; None: every
    candidate; a model without a calibration gives no confidence, so it reports every
    candidate, and `on_note(message)` hears so: by default a warning). The best
    `policy.check_candidates` candidates are checked geometrically (0: none, the
    cheaper path). `verify`: also estimate every reported pair's relative pose and keep
    the accepted ones; `pose=True` without `verify` estimates it and keeps every pair.
    `on_pose_error(message)` hears of a pair whose pose cannot be estimated (that pair
    is left out); by default it is a warning.
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
        min_confidence: float | None = LOOP_MIN_CONFIDENCE,
        verify: bool = False,
        pose: bool | None = None,
        topk: int = 1,
        rerank: int | None = None,
        device: str = "cpu",
        pose_config: Any = None,
        on_pose_error: Callable[[str], None] | None = None,
        side_views: float = 0.0,
        policy: Any = None,
        on_note: Callable[[str], None] | None = None,
    ):
        if exclude_frames is not None and (
            isinstance(exclude_frames, bool) or int(exclude_frames) != exclude_frames
        ):
            raise DiscoError(f"exclude_frames must be an integer >= 1, not {exclude_frames!r}")
        self.exclude_frames = _check_window(exclude_frames, "exclude_frames", 1)
        self.exclude_seconds = _check_window(exclude_seconds, "exclude_seconds", 0.0)
        self.exclude_distance = _check_window(exclude_distance, "exclude_distance", 0.0)
        self.threshold = _check_window(threshold, "threshold", 0.0)
        if min_confidence is not None and not (
            isinstance(min_confidence, (int, float))
            and not isinstance(min_confidence, bool)
            and 0.0 <= min_confidence <= 1.0
        ):
            raise DiscoError(f"min_confidence must lie in [0, 1], not {min_confidence!r}")
        self.min_confidence = min_confidence
        if isinstance(topk, bool) or not isinstance(topk, int) or topk < 1:
            raise DiscoError(f"topk must be an integer >= 1, not {topk!r}")
        self.topk = topk
        try:
            self.side_offsets = side_offsets(side_views)
        except ValueError as exc:
            raise DiscoError(str(exc)) from None
        self.verify = bool(verify)
        self.pose_config = pose_config
        self._model = _load_model(model, device)
        # The query stage's settings (`QueryPolicy`; default: the model's).
        self.policy = policy_for(self._model, policy, rerank=rerank)
        self._pose = bool(verify or pose)
        self._on_pose_error = on_pose_error or (lambda msg: warnings.warn(msg, stacklevel=3))
        # Told with the first scan, not here: a command that fails before it (a damaged
        # map) says only why it failed.
        self._untold: str | None = None
        if self.min_confidence is not None and not calibrated(self._model):
            self._untold = (
                f"model {self._model.name} has no calibrated confidence: every candidate is "
                "reported (cut them with threshold, --max-distance)"
            )
            self.min_confidence = None
        self._on_note = on_note or (lambda msg: warnings.warn(msg, stacklevel=4))
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

    @property
    def estimate_pose(self) -> bool:
        """Whether the detector needs each scan's points: to check candidates, or for
        the relative pose of every loop."""
        return self._pose or self.policy.check_candidates > 0

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
        limit: int | None = None,
    ) -> list[Loop]:
        """`add` for a scan embedded already (by `model.embed`); `points` is its point
        array or a function that reads it (needed when candidates are checked or poses
        estimated); `side_signatures` `[V, D]` its side views' (when the detector has
        side views); `limit`: search only the first `limit` scans (an evaluation's own
        window, in place of the detector's)."""
        i = len(self)
        if self._untold is not None:
            self._on_note(self._untold)
            self._untold = None
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
        limit = self._limit(i, t, travelled) if limit is None else min(int(limit), i)
        loops: list[Loop] = []
        if limit > 0:
            depth = self.policy.check_candidates
            found = match_queries(
                self._index,
                np.arange(i),
                self._store,
                self._model,
                sig[None],
                np.asarray(features, dtype=np.float32)[None],
                max(self.topk, depth),
                self.policy,
                limit=[limit],
                max_distance=self.threshold,
            )[0]
            rows = self._checked(i, label, found, depth)[: self.topk]
            loops = [lp for m in rows if (lp := self._loop(i, label, t, m)) is not None]
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
        with batches.embedded(  # looked up at each call: tests replace it
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

    def _checked(self, i: int, label: str, found: list, depth: int) -> list[Match]:
        """The search's rows as `Match`es, the best `depth` checked (`verification.py`)."""
        if depth == 0 or not found:
            return [as_match(m) for m in found]
        try:
            query_points = self._points.get(i)
        except DiscoError as exc:
            self._on_pose_error(f"{label}: its candidates are not checked ({exc})")
            return [as_match(m) for m in found]
        return check_candidates(
            self._model,
            found,
            query_points,
            self._row_points,
            depth,
            config=self.pose_config,
            promote_below=self.policy.check_promotes_below,
        )

    def _row_points(self, row: Match) -> np.ndarray:
        return self._points.get(row.match_id)

    def _confident(self, m: Match) -> bool:
        return self.min_confidence is None or (
            m.confidence is not None and m.confidence >= self.min_confidence
        )

    def _loop(self, i: int, label: str, t: float, m: Match) -> Loop | None:
        # A checked row's confidence is final (the ICP adds none): the bar comes first,
        # so that only the loops kept pay for their ICP (tens of ms each).
        if m.verified and not self._confident(m):
            return None
        if m.T is None and self._pose:
            try:
                query_points = self._points.get(i)
            except DiscoError as exc:
                self._on_pose_error(f"{label} -> {m.name}: no relative pose ({exc})")
                return None
            m = check_row(self._model, m, query_points, self._row_points, True, self.pose_config)
            if m.T is None:
                # One unusable pair (a scan with no valid points) must not cost the others.
                self._on_pose_error(f"{label} -> {m.name}: {m.reason}")
                return None
        if self.verify and not m.accepted:
            return None
        if not self._confident(m):
            return None
        base = {
            "query_index": i,
            "match_index": m.match_id,
            "distance": m.distance,
            "yaw_deg": m.yaw_deg,
            "query": label,
            "match": m.name,
            "query_time": t,
            "match_time": float(self._times[m.match_id]),
            "yaw_conf": m.yaw_conf,
            "confidence": m.confidence,
        }
        return Loop(**base, **(_pose_of(m) if m.T is not None else {}))


def _pose_of(m: Match) -> dict[str, Any]:
    """A checked `Match`'s pose fields, as `pose_fields` gives them for a `Loop`."""
    keys = ("T", "fitness", "rmse", "accepted", "reason", "roll_deg", "pitch_deg")
    return {k: getattr(m, k) for k in keys}
