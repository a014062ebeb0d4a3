"""`Map`: a map database you add scans to and localize scans against, from Python.

    with Map.create("map.db", model="default") as m:
        m.add(points, name="scan-0", pose=T_world_sensor)      # N x 3 / N x 4 array
    with Map.open("map.db") as m:
        for match in m.query(points, topk=3, pose=True):
            print(match.name, match.distance, match.yaw_deg, match.T)

A map is the same SQLite file `disco build-db` writes (docs/database.md): one
transaction per batch, so a crash keeps every finished batch, and readers opened
meanwhile see a consistent state. Frames and units of the results: `localize.py`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.embedding import batches
from disco_cli.embedding.batches import embed_one
from disco_cli.embedding.load import array_points
from disco_cli.errors import DatabaseError, DiscoError, ScanReadError
from disco_cli.io.readers import read_scan
from disco_cli.maps.database import DamagedRows, ModelInfo, damaged_line
from disco_cli.maps.index import check_index_kind
from disco_cli.maps.map_side_views import side_offsets, side_views_m
from disco_cli.maps.store import MapStore
from disco_cli.maps.writing import MapWriting, map_address, store_class
from disco_cli.model import MODELS, check_device, load_model
from disco_cli.query.localize import Match, PointCache, as_match
from disco_cli.query.query_policy import policy_for
from disco_cli.query.search import match_queries
from disco_cli.query.verification import check_candidates
from disco_cli.runtime.threads import get_threads

__all__ = ["Map", "QueryResult", "model_for_database", "stored_embeddings"]


def model_for_database(db: MapStore, model: Any = None, device: str = "cpu") -> tuple[Any, str]:
    """The model that built `db` and how it was named: `model` (a name, a checkpoint path
    or a loaded model) when given, which must be the same; else the stored one."""
    if model is not None and not isinstance(model, (str, Path)):
        net, source = model, str(getattr(model, "name", "model"))
    else:
        source = str(model or db.meta.get("model_source") or db.model.name)
        if model is None and source not in MODELS and not Path(source).is_file():
            # Name the file the map remembers: the user may know where it went.
            was = db.meta.get("model_source") or f"model '{db.model.name}'"
            raise DatabaseError(
                db.path, f"built with checkpoint {was}, which is gone; pass --model PATH"
            )
        net = load_model(source, device=device)
    db.check_model(ModelInfo.of(net))
    return net, source


def _model_source(model: Any) -> str:
    """How `Map.open` finds the model again: a registry name or a checkpoint's full path."""
    if not isinstance(model, (str, Path)):
        return str(getattr(model, "name", "model"))
    return str(model) if str(model) in MODELS else str(Path(model).resolve())


def _load_model(model: Any, device: str) -> Any:
    check_device(device)
    return load_model(model, device=device) if isinstance(model, (str, Path)) else model


@dataclass
class QueryResult:
    """One query of `Map.query_files`: its matches, or the error that stopped it."""

    index: int  # position in the input
    name: str
    matches: list[Match]
    error: DiscoError | None = None

    def rows(
        self, shown: Callable[[str], str], keys: list[str], verify: bool = False
    ) -> tuple[list[dict[str, Any]], list[str]]:
        """`disco query`'s rows of this result (the `keys` of each match, the match's
        stored name as `shown`) and the errors to report: the query's own, or one per
        match whose pose could not be estimated (it gets no row). `verify` keeps only
        the matches whose pose is accepted; a match whose scan is missing keeps its
        row, with the pose columns empty."""
        if self.error is not None:
            return [], [str(self.error)]
        rows, errors = [], []
        for mt in self.matches:
            if mt.T is None and mt.accepted is False:
                errors.append(f"{shown(mt.name)}: {mt.reason}")
            elif mt.accepted or not verify:
                row = {**mt.as_dict(), "query": self.name, "match": shown(mt.name)}
                rows.append({k: row.get(k) for k in keys})
        return rows, errors


class Map(MapWriting):
    """A map database of scan signatures. Use `Map.create(path)` or `Map.open(path)`.

    `len(map)` is the number of scans; `map.model` the model that embeds them. A map
    opened read-only answers from a snapshot taken at its first query (`refresh()`
    takes a new one), so a build appending at the same time never shows half a batch.
    """

    def __init__(
        self,
        path: Path,
        db: MapStore | None,
        model: Any,
        source: str,
        writable: bool,
        overwrite: bool = False,
    ):
        self.path = path
        self._db = db
        self._model = model
        self._source = source
        self._writable = writable
        self._overwrite = overwrite
        self._closed = False
        self._snapshot: tuple[np.ndarray, Any] | None = None  # ids, SignatureIndex
        self.side_offsets: tuple[float, ...] = () if db is None else db.side_offsets
        self._xy: np.ndarray | None = None  # stored x, y of the snapshot's scans
        self._real: np.ndarray | None = None  # their files' real paths
        self._points = PointCache(self._read_match, size=32)
        self._missing: set[str] = set()
        self.scan_root: str | Path | None = None
        # Which signature index answers (disco_cli.maps.index: auto, exact or ann), and who
        # is told when an approximate index is built or its sidecar cannot be used.
        self.index_kind = "auto"
        self.on_index_note: Callable[[str], None] = lambda msg: warnings.warn(msg, stacklevel=4)
        # Told once per stored scan that cannot be found or read (default: a warning).
        self.on_missing_scan: Callable[[str], None] = lambda msg: warnings.warn(msg, stacklevel=4)
        # Told once per read that finds damaged rows, which are then left out (one line).
        self.on_damaged: Callable[[str], None] = lambda msg: warnings.warn(msg, stacklevel=4)
        self._skipped: set[int] = set()  # damaged scans told of and left out

    # -- opening and closing --------------------------------------------------

    @classmethod
    def create(
        cls,
        path: str | Path,
        model: Any = "default",
        *,
        overwrite: bool = False,
        device="cpu",
        side_views: float = 0.0,
    ) -> Map:
        """A new, empty map at `path` for `model` (a name, a checkpoint path or a model
        object). The file appears with the first batch added; an existing file is refused
        unless `overwrite` (it is replaced when the first batch is written).
        `side_views` (metres, 0 = none) also stores each scan's signatures seen from that
        far to its left and right, for queries that drive beside the map's line
        (`map_side_views.py`; about 3x the embedding time when adding)."""
        path = map_address(path)
        if path.exists() and not overwrite:
            raise DatabaseError(path, "already exists; use Map.open to add to it")
        try:
            offsets = side_offsets(side_views)
        except ValueError as exc:
            raise DiscoError(str(exc)) from None
        net = _load_model(model, device)
        m = cls(path, None, net, _model_source(model), True, overwrite)
        m.side_offsets = offsets
        return m

    @classmethod
    def open(
        cls,
        path: str | Path,
        *,
        writable: bool = False,
        model: Any = None,
        device: str = "cpu",
        scan_root: str | Path | None = None,
        index: str = "auto",
        on_note: Callable[[str], None] | None = None,
    ) -> Map:
        """An existing map. `model` defaults to the one that built it; another is refused.
        A stored scan (read for poses) is found at its stored path, else relative to the
        map's folder, else under `scan_root` (docs/database.md). `index`: the signature
        search, `exact`, `ann` (approximate, for maps of millions of scans; needs
        `pip install 'disco-cli[ann]'`) or `auto` (ann from 200,000 scans when installed;
        `disco_cli.maps.index`). A map this process may not write opens read-only (unless
        `writable`, which is then refused) and `on_note` hears one line saying so
        (default: `note: ...` on stderr; `Database.open`)."""
        check_device(device)
        check_index_kind(index)
        db = store_class(path).open(path, writable=writable, on_note=on_note)
        try:
            net, source = model_for_database(db, model, device)
        except BaseException:
            db.close()
            raise
        m = cls(map_address(path), db, net, source, writable)
        m.scan_root = scan_root
        m.index_kind = index
        return m

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
        self._db = None
        self._snapshot = None
        self._closed = True

    def __enter__(self) -> Map:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise DatabaseError(self.path, "the map is closed")

    # -- what it holds ----------------------------------------------------------

    @property
    def model(self) -> Any:
        """The model that embeds scans for this map (`load_model`'s protocol)."""
        return self._model

    @property
    def side_views(self) -> float:
        """How far to each side the map's side views look (metres; 0: none)."""
        return side_views_m(self.side_offsets)

    @property
    def database(self) -> MapStore | None:
        """The underlying store (`store.MapStore`: a `Database`, or a `MilvusDatabase` for
        a `milvus:` address; None for a new map before its first scan)."""
        return self._db

    def __len__(self) -> int:
        self._check_open()
        if self._db is None:
            return 0
        if not self._writable:
            return len(self._index()[0])
        return len(self._db)

    def names(self) -> list[str]:
        """Every stored name (path), in id order."""
        self._check_open()
        return [] if self._db is None else self._db.paths()

    def near(self, xy: Any, radius: float, path: str | None = None) -> np.ndarray:
        """Ids of the scans whose stored pose is within `radius` m of `xy` (x, y, or a
        4 x 4 pose; NaN: none), and of the stored scan of the file `path` itself when
        given (a query that is in the map); scans without a pose are never near."""
        self._check_open()
        if self._db is None:
            return np.empty(0, np.int64)
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape == (4, 4):
            xy = xy[:2, 3]
        ids, _ = self._index()
        if self._xy is None or len(self._xy) != len(ids):
            self._xy = self._db.poses()[0][self._snapshot_rows(), :2]
            self._tell_damaged()
        stored = self._xy
        d = np.hypot(stored[:, 0] - xy[0], stored[:, 1] - xy[1])
        near = d <= radius  # unknown poses give NaN: never near
        if path is not None:
            if self._real is None or len(self._real) != len(ids):
                names = self.names()
                self._real = np.array([os.path.realpath(names[r]) for r in self._snapshot_rows()])
            near |= self._real == os.path.realpath(path)
        return ids[near]

    def _snapshot_rows(self) -> np.ndarray:
        """Where the snapshot's scans are among every stored row (`Database.ids`): the
        snapshot leaves out damaged scans and those appended since it was taken."""
        ids, _ = self._index()
        return np.searchsorted(self._db.ids(), ids)  # type: ignore[union-attr]

    def _tell_damaged(self) -> None:
        """One warning line naming the damaged scans found since the last one."""
        if self._db is None:
            return
        new = {i: p for i, p in self._db.damaged.items() if i not in self._skipped}
        if new:
            self._skipped |= set(new)
            self.on_damaged(f"{self.path}: {damaged_line(new, self.path)}")

    def stored(self, names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`(found [N] bool, signatures [N, D], features [N, ...])` of the scan files
        `names` as stored (matched by where the stored scans are now; rows of scans not
        stored are zero), for reusing a map's embeddings."""
        self._check_open()
        n = len(names)
        if self._db is None:
            return np.zeros(n, bool), np.zeros((n, 0), np.float32), np.zeros((n, 0), np.float32)
        ids, index = self._index()
        # By where the stored scans are now, so that it works from any directory and for
        # a map that moved (Database.locate).
        locations = self._db.locations(self.scan_root)
        where = {locations[r]: k for k, r in enumerate(self._snapshot_rows())}
        rows = np.array([where.get(os.path.abspath(p), -1) for p in names], dtype=np.int64)
        while True:
            found = (rows >= 0) & ~np.isin(ids[np.maximum(rows, 0)], list(self._skipped))
            try:
                stored = self._db.rows(ids[rows[found]]) if found.any() else None
                break
            except DamagedRows as exc:  # embedded again by the caller, like a scan not stored
                if set(exc.ids) <= self._skipped:
                    raise
                self._tell_damaged()
        self._tell_damaged()
        sigs = np.zeros((n, index.dim), np.float32)
        feats = np.zeros((n, *self._db.feature_shape), np.float32)
        if stored is not None:
            sigs[found] = index.matrix[rows[found]]
            feats[found] = stored.features
        return found, sigs, feats

    # -- localizing ---------------------------------------------------------------

    def refresh(self) -> None:
        """Take a new snapshot of the stored scans (a read-only map sees scans added by
        another process only after this)."""
        self._check_open()
        self._snapshot = None

    def _index(self) -> tuple[np.ndarray, Any]:
        self._check_open()
        if self._db is None:
            raise DatabaseError(self.path, "the database is empty")
        if self._snapshot is None:
            # Each store picks its index: a Milvus map searches in Milvus.
            self._snapshot = self._db.index_for(self.index_kind, self.on_index_note)
            self._xy = self._real = None
            self._tell_damaged()
        return self._snapshot

    def _exclude_rows(self, exclude: Any) -> np.ndarray | None:
        if exclude is None:
            return None
        ids, _ = self._index()
        ex = np.asarray(exclude)
        if ex.dtype == bool:
            if ex.shape != (len(ids),):
                raise DiscoError(f"exclude: a mask must have one entry per scan ({len(ids)})")
            return ex
        rows = np.searchsorted(ids, ex.astype(np.int64).reshape(-1))
        mask = np.zeros(len(ids), bool)
        ok = rows < len(ids)
        mask[rows[ok][ids[rows[ok]] == ex.reshape(-1)[ok]]] = True
        return mask

    def locate(self, name: str) -> Path | None:
        """Where the stored scan `name` is now (`Database.locate`), or None."""
        self._check_open()
        return None if self._db is None else self._db.locate(name, self.scan_root)

    def shown(self, name: str) -> str:
        """A stored scan's path as printed: where it is now (else as stored), relative to
        the current directory when it lies under it, else absolute."""
        where = self.locate(name)
        full = os.path.abspath(where if where is not None else name)
        rel = os.path.relpath(full)
        return full if rel.startswith(os.pardir) else rel

    def _read_match(self, name: str) -> np.ndarray:
        if name in self._missing:
            raise ScanReadError(name, "not found (nor beside the database)")
        where = self.locate(name)
        try:
            if where is None:
                raise ScanReadError(name, "not found (nor beside the database)")
            return read_scan(where)
        except ScanReadError as exc:
            self._missing.add(name)
            hint = "" if self.scan_root else "; --scan-root DIR says where the map's scans are"
            self.on_missing_scan(f"{exc}: no relative pose for this match{hint}")
            raise

    def _search(
        self,
        signature: np.ndarray,
        features: np.ndarray,
        topk: int,
        policy: Any,
        exclude: Any,
        max_distance: float | None,
    ) -> list:
        ids, index = self._index()
        mask = self._exclude_rows(exclude)
        while True:  # each pass leaves out the damaged rows the last one met
            if self._skipped:
                skip = np.isin(ids, list(self._skipped))
                mask = skip if mask is None else mask | skip
            try:
                return match_queries(
                    index,
                    ids,
                    self._db,
                    self._model,
                    signature[None],
                    features[None],
                    topk,
                    policy,
                    exclude=mask,
                    max_distance=max_distance,
                )[0]
            except DamagedRows as exc:
                if set(exc.ids) <= self._skipped:
                    raise
                self._tell_damaged()

    def query(
        self,
        points: Any,
        *,
        topk: int = 10,
        pose: bool = False,
        verify: bool = False,
        rerank: int | None = None,
        exclude: Any = None,
        max_distance: float | None = None,
        name: str = "points",
        refine_yaw: int | None = None,
        snap_radius: float | None = None,
        policy: Any = None,
        min_confidence: float | None = None,
    ) -> list[Match]:
        """The `topk` best matches of one scan (an N x 3 or N x 4 array), best first.

        `pose` adds the refined pose T_match<-query of each (read from the match's
        stored path); `verify` keeps only the matches whose pose is accepted (implies
        `pose`). `rerank`: how many nearest signatures to re-rank (default: the
        model's; DiSCO goes on down to 40 where none of them matches well).
        `exclude`: match ids (or a boolean mask over the map) to leave out;
        `max_distance` drops worse matches. `name` names the scan in errors.
        `refine_yaw`: how many best matches get the parallax-free yaw (default 1).
        `snap_radius`: where the map has poses, the first match is the one nearest the
        query's estimated position among those within this many metres of the best
        (default: the model's, 5 m for DiSCO; 0: the best re-ranked).
        `policy`: a `QueryPolicy` for all of the query stage's settings (default: the
        model's); `rerank`, `refine_yaw` and `snap_radius` change it.
        Each match carries `confidence`, the estimated probability that it is a true
        revisit (query/confidence.py); the best `policy.check_candidates` are checked
        geometrically first where the map's scans can be read (query/verification.py).
        `min_confidence` drops matches below it.
        """
        self._check_open()
        pts = array_points(points, name)
        sig, feat = embed_one(pts, self._model, name)
        policy = policy_for(
            self._model, policy, rerank=rerank, refine_yaw=refine_yaw, snap_radius=snap_radius
        )
        found = self._search(sig, feat, topk, policy, exclude, max_distance)
        return _confident(self._finish(found, pts, policy, pose or verify, verify), min_confidence)

    def _finish(self, found: list, points: Any, policy: Any, pose: bool, verify: bool) -> list:
        """The search's rows as `Match`es: every one with its pose (`pose`; only the
        accepted with `verify`), or the best few checked (`policy.check_candidates`)."""
        if pose:
            return check_candidates(
                self._model,
                found,
                points,
                self._pose_points,
                0,
                pose=True,
                verify=verify,
                promote_below=policy.check_promotes_below,
            )
        if policy.check_candidates and points is not None:
            return check_candidates(
                self._model,
                found,
                points,
                self._checkable_points,
                policy.check_candidates,
                promote_below=policy.check_promotes_below,
            )
        return [as_match(m) for m in found]

    def _pose_points(self, row: Match) -> np.ndarray:
        """A map scan's points for a relative pose (a missing file is told once)."""
        return self._points.get(row.name)

    def _checkable_points(self, row: Match) -> np.ndarray:
        """A map scan's points for the geometric check, quietly refused where its file
        is not found (a map of arrays has none; `--pose` is where that is said)."""
        name = row.name
        if name in self._missing or self.locate(name) is None:
            raise ScanReadError(name, "not found")
        return self._points.get(name)

    def query_many(self, scans: Iterable[Any], **options: Any) -> Iterator[list[Match]]:
        """`query` of each scan in turn, yielded as each is done (same options)."""
        for points in scans:
            yield self.query(points, **options)

    def query_files(
        self,
        paths: Iterable[str],
        *,
        topk: int = 10,
        pose: bool = False,
        rerank: int | None = None,
        exclude: Callable[[int, str], Any] | None = None,
        max_distance: float | None = None,
        threads: int | None = None,
        scan_format: str | None = None,
        refine_yaw: int | None = None,
        snap_radius: float | None = None,
        policy: Any = None,
        min_confidence: float | None = None,
    ) -> Iterator[QueryResult]:
        """Query scan files, streamed: reading and voxelizing run ahead on `threads`
        threads (None: `disco_cli.get_threads()`), and each result is yielded as soon as
        it is ready, in input order.
        A scan that fails yields its error and the others go on. `exclude(index, path)`
        gives the match ids to leave out for each query. With `pose`, rows whose pose
        could not be estimated have `T` None and the reason in `reason`."""
        self._check_open()
        policy = policy_for(
            self._model, policy, rerank=rerank, refine_yaw=refine_yaw, snap_radius=snap_radius
        )
        threads = get_threads() if threads is None else threads
        with batches.embedded(  # looked up at each call: tests replace it
            paths,
            self._model,
            1,
            threads,
            scan_format,
            prefetch=2 * threads,
            keep_points=pose or policy.check_candidates > 0,
        ) as chunks:
            for chunk in chunks:
                for item in chunk.errors:
                    yield QueryResult(item.index, item.path, [], item.error)
                for j, item in enumerate(chunk.items):
                    try:
                        ex = None if exclude is None else exclude(item.index, item.path)
                        found = self._search(
                            chunk.signatures[j],
                            chunk.features[j],
                            topk,
                            policy,
                            ex,
                            max_distance,
                        )
                    except DiscoError as exc:
                        yield QueryResult(item.index, item.path, [], exc)
                        continue
                    matches = self._finish(found, item.points, policy, pose, False)
                    matches = _confident(matches, min_confidence)
                    item.points = None
                    yield QueryResult(item.index, item.path, matches)


def _confident(matches: list[Match], min_confidence: float | None) -> list[Match]:
    """The matches whose confidence is at least `min_confidence` (None: all)."""
    if min_confidence is None:
        return matches
    return [m for m in matches if m.confidence is not None and m.confidence >= min_confidence]


def stored_embeddings(
    path: str | Path, names: list[str], model: Any, *, scan_root: Any = None, warn: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`Map.stored(names)` of the map at `path`, which `model` must have built (for
    `LoopDetector.add_files`'s `stored`); `warn` hears when it holds none of them."""
    with Map.open(path, model=model, scan_root=scan_root) as m:
        if warn is not None:
            m.on_damaged = warn
        found = m.stored(names)
    if not found[0].any():
        (warn or warnings.warn)(f"{path}: holds none of these scans; embedding them all")
    return found
