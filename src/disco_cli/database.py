"""The map database: one SQLite file (WAL journal) of scan signatures, features and poses.

Layout (format version 1):

- `meta(key, value)`: `format_version`, `disco_version`, `model_name`, `fingerprint`,
  `model_config` and `bev_config` (JSON), `signature_dim`, `feature_shape` (JSON),
  `feature_dtype`.
- `scans(id, path, time, x, y, z, yaw, signature, features, feature_scale, rel_path)`:
  one row per scan, `id` in insertion order (1, 2, ...), `path` absolute (unique; a
  database written before disco stored absolute paths holds them as the user gave
  them), `rel_path` the same scan relative to the database's folder (NULL when there
  is no such path, and absent from databases written before it existed),
  time and pose NULL when unknown, `signature` float32 little-endian, `features`
  float16 little-endian divided by `feature_scale` (the largest magnitude, so that
  float16 neither overflows nor loses small features).
- `side_views(scan_id, offset_m, signature)`: only in a map built with side views
  (meta `side_views_m`, a JSON list of offsets in metres): the signatures of each scan
  re-centred `offset_m` to its side (`side_views.py`), searched beside the scans'.

Every append is one transaction, so a crash or Ctrl-C leaves every finished batch and
nothing half-written; readers opened meanwhile see a consistent state (WAL). A new
database is written to a hidden temporary file and renamed into place only when its
first batch is committed, so no half-initialized file is ever left at the target.

Opening checks the whole file before anything else touches it: the SQLite header and
the file's size (a cut file is named as such), then `PRAGMA integrity_check` (every
page, every b-tree, the index). A damaged file is refused with one `DatabaseError`
naming it and the problem, and is left byte for byte as it was; any SQLite error met
later is turned into a `DatabaseError` too, never passed on as `sqlite3.DatabaseError`.
"""

from __future__ import annotations

import functools
import json
import os
import sqlite3
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from disco_cli.errors import DatabaseError

__all__ = ["FORMAT_VERSION", "Database", "ModelInfo", "ScanBatch", "MatchRows", "stored_paths"]

FORMAT_VERSION = 1
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER_SIZE = 100
# At most this many problems of the integrity check are named in the error line.
_PROBLEMS_SHOWN = 3
_SIG_DTYPE = np.dtype("<f4")
_FEAT_DTYPE = np.dtype("<f2")

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE scans (
    id INTEGER PRIMARY KEY,
    path TEXT NOT NULL UNIQUE,
    time REAL,
    x REAL, y REAL, z REAL, yaw REAL,
    signature BLOB NOT NULL,
    features BLOB NOT NULL,
    feature_scale REAL NOT NULL,
    rel_path TEXT
);
"""
_SIDE_SCHEMA = """
CREATE TABLE side_views (
    scan_id INTEGER NOT NULL,
    offset_m REAL NOT NULL,
    signature BLOB NOT NULL,
    PRIMARY KEY (scan_id, offset_m)
)
"""
_SCAN_COLUMNS = {
    "id",
    "path",
    "time",
    "x",
    "y",
    "z",
    "yaw",
    "signature",
    "features",
    "feature_scale",
}


@dataclass(frozen=True)
class ModelInfo:
    """What a database records about the model that built it; another model is refused."""

    name: str
    fingerprint: str
    model_config: dict
    bev_config: dict

    @classmethod
    def of(cls, model: Any) -> ModelInfo:
        return cls(
            name=str(model.name),
            fingerprint=str(model.fingerprint),
            model_config=_jsonable(model.config_dict()),
            bev_config=_jsonable(model.bev_config.to_dict()),
        )


def _jsonable(d: dict) -> dict:
    # A round trip through JSON so that comparisons see what the database stores.
    return json.loads(json.dumps(d, sort_keys=True, default=_json_default))


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


@dataclass
class ScanBatch:
    """Scans to append: `poses` is `[B, 4]` (x, y, z, yaw rad) and `times` `[B]`, NaN = unknown."""

    paths: list[str]
    signatures: np.ndarray
    features: np.ndarray
    poses: np.ndarray | None = None
    times: np.ndarray | None = None
    rel_paths: list[str | None] | None = None  # relative to the database's folder
    # Side views (`side_views.py`): the offsets and `[B, V, D]` signatures, or none.
    side_offsets: tuple[float, ...] = ()
    side_signatures: np.ndarray | None = None

    def __post_init__(self) -> None:
        b = len(self.paths)
        self.side_offsets = tuple(float(o) for o in self.side_offsets)
        if self.side_offsets:
            v = len(self.side_offsets)
            self.side_signatures = np.asarray(self.side_signatures, dtype=np.float32)
            if self.side_signatures.shape[:2] != (b, v) or self.side_signatures.ndim != 3:
                raise ValueError(
                    f"side signatures must be [{b}, {v}, D], got {self.side_signatures.shape}"
                )
        elif self.side_signatures is not None and np.size(self.side_signatures):
            raise ValueError("side signatures given without their offsets")
        if self.rel_paths is None:
            self.rel_paths = [None] * b
        if len(self.rel_paths) != b:
            raise ValueError(f"rel_paths must have {b} entries, got {len(self.rel_paths)}")
        self.signatures = np.asarray(self.signatures, dtype=np.float32)
        self.features = np.asarray(self.features, dtype=np.float32)
        if self.signatures.ndim != 2 or len(self.signatures) != b:
            raise ValueError(f"signatures must be [{b}, D], got {self.signatures.shape}")
        if self.features.ndim < 2 or len(self.features) != b:
            raise ValueError(f"features must be [{b}, ...], got {self.features.shape}")
        if self.poses is None:
            self.poses = np.full((b, 4), np.nan)
        self.poses = np.asarray(self.poses, dtype=np.float64)
        if self.poses.shape != (b, 4):
            raise ValueError(f"poses must be [{b}, 4], got {self.poses.shape}")
        if self.times is None:
            self.times = np.full(b, np.nan)
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        if self.times.shape != (b,):
            raise ValueError(f"times must be [{b}], got {self.times.shape}")


@dataclass
class MatchRows:
    """Stored data of some scans, in the order asked for."""

    ids: np.ndarray
    paths: list[str]
    poses: np.ndarray  # [K, 4] x, y, z, yaw (rad), NaN = unknown
    features: np.ndarray  # [K, ...] float32


def _none_if_nan(v: float) -> float | None:
    return None if not np.isfinite(v) else float(v)


def _encode_features(f: np.ndarray) -> tuple[bytes, float]:
    scale = float(np.max(np.abs(f))) if f.size else 0.0
    if not np.isfinite(scale):
        raise ValueError("features are not finite")
    if scale == 0.0:
        scale = 1.0
    return (f / scale).astype(_FEAT_DTYPE).tobytes(), scale


_F = TypeVar("_F", bound=Callable[..., Any])


def _sql_errors(func: _F) -> _F:
    """Turn an SQLite error met while reading or writing into one `DatabaseError`
    naming the file: a page that turns out damaged only when it is read, a disk error."""

    @functools.wraps(func)
    def wrapper(self: Database, *args: Any, **kwargs: Any) -> Any:
        try:
            return func(self, *args, **kwargs)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(self.path, f"corrupt or unreadable database ({exc})") from None

    return wrapper  # type: ignore[return-value]


class Database:
    """An open map database. Use `Database.open(path)` or `Database.create(path, ...)`."""

    def __init__(self, path: Path, conn: sqlite3.Connection, meta: dict[str, str]):
        self.path = path
        self._conn = conn
        self.meta = meta
        self.format_version = int(meta["format_version"])
        self.model = ModelInfo(
            name=meta["model_name"],
            fingerprint=meta["fingerprint"],
            model_config=json.loads(meta["model_config"]),
            bev_config=json.loads(meta["bev_config"]),
        )
        self.signature_dim = int(meta["signature_dim"])
        self.feature_shape = tuple(int(v) for v in json.loads(meta["feature_shape"]))
        try:
            columns = {r[1] for r in conn.execute("PRAGMA table_info(scans)")}
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(path, f"corrupt or unreadable database ({exc})") from None
        # Databases written before relative paths were stored lack the column.
        self._has_rel = "rel_path" in columns
        try:
            offsets = json.loads(meta.get("side_views_m", "[]"))
            self.side_offsets: tuple[float, ...] = tuple(float(o) for o in offsets)
        except (ValueError, TypeError):
            raise DatabaseError(path, "corrupt database: unreadable side_views_m") from None
        if self.side_offsets:
            try:
                tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
            except sqlite3.DatabaseError as exc:
                raise DatabaseError(path, f"corrupt or unreadable database ({exc})") from None
            if "side_views" not in tables:
                raise DatabaseError(path, "corrupt database: side views named but not stored")

    # -- opening --------------------------------------------------------------

    @classmethod
    def open(cls, path: str | Path, writable: bool = False, verify: bool = True) -> Database:
        """Open an existing database; raise `DatabaseError` naming the problem otherwise.

        `verify` (the default, and always for writing) runs SQLite's integrity check over
        the whole file first, so that a damaged file is refused before it is read or
        written; it reads every page once (about 0.5 s per 20,000 scans from the page
        cache). A refused file is not modified.
        """
        path = Path(path)
        if not path.exists():
            raise DatabaseError(path, "no such database")
        if not path.is_file():
            raise DatabaseError(path, "not a file")
        _check_header(path)
        conn = _connect(path, writable)
        try:
            if verify or writable:
                _check_integrity(path, conn)
            meta = _read_meta(path, conn)
            _check_scans_table(path, conn)
            if writable:
                conn.execute("PRAGMA journal_mode=WAL")
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise DatabaseError(path, f"corrupt or unreadable database ({exc})") from None
        except BaseException:
            conn.close()
            raise
        return cls(path, conn, meta)

    @classmethod
    def create(
        cls,
        path: str | Path,
        model: ModelInfo,
        first: ScanBatch,
        disco_version: str = "",
        extra_meta: dict[str, str] | None = None,
    ) -> Database:
        """Create a new database holding `first` (which must not be empty).

        The file appears at `path` only once its first batch is committed: it is built
        under a temporary name and renamed into place.
        """
        path = Path(path)
        if path.exists():
            raise DatabaseError(path, "already exists")
        if not first.paths:
            raise ValueError("the first batch of a new database must not be empty")
        if not disco_version:
            from disco_cli import __version__ as disco_version
        tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
        meta = {
            "format_version": str(FORMAT_VERSION),
            "disco_version": disco_version,
            "model_name": model.name,
            "fingerprint": model.fingerprint,
            "model_config": json.dumps(model.model_config, sort_keys=True),
            "bev_config": json.dumps(model.bev_config, sort_keys=True),
            "signature_dim": str(first.signatures.shape[1]),
            "feature_shape": json.dumps(list(first.features.shape[1:])),
            "feature_dtype": "float16",
            **(extra_meta or {}),
        }
        if first.side_offsets:
            meta["side_views_m"] = json.dumps(list(first.side_offsets))
        try:
            tmp.unlink(missing_ok=True)
            conn = sqlite3.connect(tmp)
            try:
                with conn:
                    for stmt in _SCHEMA.strip().split(";"):
                        if stmt.strip():
                            conn.execute(stmt)
                    if first.side_offsets:
                        conn.execute(_SIDE_SCHEMA)
                    conn.executemany("INSERT INTO meta VALUES (?, ?)", sorted(meta.items()))
                cls(path, conn, meta).append(first)
            finally:
                conn.close()
            # Another build may have created the target meanwhile: never overwrite it.
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise DatabaseError(path, "already exists") from None
            except OSError:
                if path.exists():
                    raise DatabaseError(path, "already exists") from None
                os.replace(tmp, path)
            tmp.unlink(missing_ok=True)
        except sqlite3.Error as exc:
            tmp.unlink(missing_ok=True)
            raise DatabaseError(path, f"cannot create ({exc})") from None
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise DatabaseError(path, f"cannot create ({exc.strerror or exc})") from None
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return cls.open(path, writable=True)

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- checks -----------------------------------------------------------------

    def check_model(self, model: ModelInfo) -> None:
        """Refuse a model or BEV configuration other than the one that built this database."""
        mine = self.model
        # The fingerprint decides (weights and configs); the same weights loaded by
        # another name (`default` or its checkpoint path) are the same model.
        if model.fingerprint != mine.fingerprint:
            raise DatabaseError(
                self.path,
                f"built with model '{mine.name}' (fingerprint {mine.fingerprint[:12]}), "
                f"not '{model.name}' (fingerprint {model.fingerprint[:12]}); "
                "use the same model or build a new database",
            )
        if model.bev_config != mine.bev_config:
            diff = sorted(
                k
                for k in set(model.bev_config) | set(mine.bev_config)
                if model.bev_config.get(k) != mine.bev_config.get(k)
            )
            raise DatabaseError(
                self.path, f"built with another BEV configuration (differs in {', '.join(diff)})"
            )

    def check_batch_shapes(self, batch: ScanBatch) -> None:
        if batch.signatures.shape[1] != self.signature_dim:
            raise DatabaseError(
                self.path,
                f"holds {self.signature_dim}-dim signatures, got {batch.signatures.shape[1]}",
            )
        if tuple(batch.features.shape[1:]) != self.feature_shape:
            raise DatabaseError(
                self.path, f"holds features {self.feature_shape}, got {batch.features.shape[1:]}"
            )
        if batch.side_offsets != self.side_offsets:
            from disco_cli.side_views import side_views_m

            def said(offsets: tuple[float, ...]) -> str:
                return f"side views at {side_views_m(offsets):g} m" if offsets else "no side views"

            raise DatabaseError(
                self.path,
                f"holds {said(self.side_offsets)}, got scans with {said(batch.side_offsets)}; "
                "add them with the map's --side-views setting or build a new map",
            )
        if batch.side_offsets and batch.side_signatures.shape[2] != self.signature_dim:  # type: ignore[union-attr]
            raise DatabaseError(self.path, "side view signatures have another dimension")

    # -- writing ----------------------------------------------------------------

    @_sql_errors
    def append(self, batch: ScanBatch) -> None:
        """Append one batch of scans in one transaction (all or nothing)."""
        if not batch.paths:
            return
        self.check_batch_shapes(batch)
        rows = []
        for i, p in enumerate(batch.paths):
            feats, scale = _encode_features(batch.features[i])
            x, y, z, yaw = (_none_if_nan(v) for v in batch.poses[i])
            row = (
                str(p),
                _none_if_nan(batch.times[i]),
                x,
                y,
                z,
                yaw,
                batch.signatures[i].astype(_SIG_DTYPE).tobytes(),
                feats,
                scale,
            )
            rel = batch.rel_paths[i]  # type: ignore[index]
            rows.append(row + (rel,) if self._has_rel else row)
        columns = "path, time, x, y, z, yaw, signature, features, feature_scale"
        if self._has_rel:
            columns += ", rel_path"
        marks = ", ".join("?" * len(rows[0]))
        try:
            with self._conn:
                if not batch.side_offsets:
                    self._conn.executemany(f"INSERT INTO scans ({columns}) VALUES ({marks})", rows)
                    return
                views = []
                for i, row in enumerate(rows):
                    cur = self._conn.execute(f"INSERT INTO scans ({columns}) VALUES ({marks})", row)
                    for k, offset in enumerate(batch.side_offsets):
                        sig = batch.side_signatures[i, k].astype(_SIG_DTYPE).tobytes()  # type: ignore[index]
                        views.append((cur.lastrowid, offset, sig))
                self._conn.executemany("INSERT INTO side_views VALUES (?, ?, ?)", views)
        except sqlite3.IntegrityError as exc:
            raise DatabaseError(self.path, f"cannot append: {exc}") from None
        except sqlite3.Error as exc:
            raise DatabaseError(self.path, f"cannot write: {exc}") from None

    # -- reading ----------------------------------------------------------------

    @_sql_errors
    def __len__(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM scans").fetchone()[0])

    @_sql_errors
    def paths(self) -> list[str]:
        """Every stored path, in id order."""
        return [r[0] for r in self._conn.execute("SELECT path FROM scans ORDER BY id")]

    @_sql_errors
    def locate(self, stored: str, scan_root: str | Path | None = None) -> Path | None:
        """Where the stored scan `stored` (a `path` of this database) is now, or None.

        In order: the stored path itself when it exists (absolute; an old database's
        relative path counts from the current directory, as it always did); then its
        path relative to the database's current folder (a map folder moved or mounted
        elsewhere as a whole); then under `scan_root`: the stored path with its leading
        folders dropped one at a time, the longest that exists there
        (`/data/kitti/00/velodyne/000005.bin` is found as
        `SCAN_ROOT/00/velodyne/000005.bin`).
        """
        rel = None
        if self._has_rel:
            row = self._conn.execute("SELECT rel_path FROM scans WHERE path = ?", (stored,))
            found = row.fetchone()
            rel = found[0] if found else None
        return _locate(stored, rel, self.path, scan_root)

    @_sql_errors
    def locations(self, scan_root: str | Path | None = None) -> list[str]:
        """Every stored scan's location now (`locate`), in id order, as absolute paths;
        a scan found nowhere keeps its stored path (made absolute)."""
        column = "rel_path" if self._has_rel else "NULL"
        out = []
        for stored, rel in self._conn.execute(f"SELECT path, {column} FROM scans ORDER BY id"):
            where = _locate(stored, rel, self.path, scan_root)
            out.append(str(where) if where is not None else os.path.abspath(stored))
        return out

    @_sql_errors
    def has_poses(self) -> bool:
        row = self._conn.execute("SELECT 1 FROM scans WHERE x IS NOT NULL LIMIT 1").fetchone()
        return row is not None

    @_sql_errors
    def signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(ids [N] int64, signatures [N, D] float32)`, in id order, read into one matrix."""
        n = len(self)
        if n == 0:
            raise DatabaseError(self.path, "the database is empty")
        ids = np.empty(n, dtype=np.int64)
        sigs = np.empty((n, self.signature_dim), dtype=np.float32)
        nbytes = self.signature_dim * _SIG_DTYPE.itemsize
        cur = self._conn.execute("SELECT id, signature FROM scans ORDER BY id")
        i = 0
        while rows := cur.fetchmany(4096):
            for rid, blob in rows:
                if i >= n:
                    break
                if len(blob) != nbytes:
                    raise DatabaseError(self.path, f"scan {rid}: signature has a wrong size")
                ids[i] = rid
                sigs[i] = np.frombuffer(blob, dtype=_SIG_DTYPE)
                i += 1
        ids, sigs = ids[:i], sigs[:i]
        # SQLite keeps no checksum of a blob: a damaged signature (NaN, or so large that
        # its squared norm overflows float32) would derail the search, so it stops here.
        rid = _first_damaged(ids, sigs)
        if rid is not None:
            raise DatabaseError(
                self.path,
                f"scan {rid}: signature is not finite or out of range (damaged?); "
                "disco info --check lists every problem",
            )
        return ids, sigs

    @_sql_errors
    def side_signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(scan ids [M], signatures [M, D])` of the stored side views (none: empty)."""
        if not self.side_offsets:
            return np.empty(0, np.int64), np.empty((0, self.signature_dim), np.float32)
        rows = self._conn.execute(
            "SELECT scan_id, signature FROM side_views ORDER BY scan_id, offset_m"
        ).fetchall()
        nbytes = self.signature_dim * _SIG_DTYPE.itemsize
        ids = np.empty(len(rows), dtype=np.int64)
        sigs = np.empty((len(rows), self.signature_dim), dtype=np.float32)
        for i, (rid, blob) in enumerate(rows):
            if not isinstance(blob, bytes) or len(blob) != nbytes:
                raise DatabaseError(self.path, f"scan {rid}: a side view has a wrong size")
            ids[i] = rid
            sigs[i] = np.frombuffer(blob, dtype=_SIG_DTYPE)
        rid = _first_damaged(ids, sigs)
        if rid is not None:
            raise DatabaseError(self.path, f"scan {rid}: a side view is not finite (damaged?)")
        return ids, sigs

    @_sql_errors
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """`(poses [N, 4] x, y, z, yaw rad, times [N])` in id order, NaN where unknown."""
        rows = self._conn.execute("SELECT x, y, z, yaw, time FROM scans ORDER BY id").fetchall()
        arr = np.array(rows, dtype=np.float64).reshape(-1, 5)  # None -> nan
        return arr[:, :4], arr[:, 4]

    @_sql_errors
    def rows(self, ids: Sequence[int] | np.ndarray) -> MatchRows:
        """Paths, poses and features of the scans `ids`, in that order (only those rows)."""
        ids = [int(i) for i in np.asarray(ids).reshape(-1)]
        found: dict[int, tuple] = {}
        for chunk in range(0, len(ids), 500):
            part = sorted(set(ids[chunk : chunk + 500]))
            marks = ",".join("?" * len(part))
            for row in self._conn.execute(
                f"SELECT id, path, x, y, z, yaw, features, feature_scale FROM scans "
                f"WHERE id IN ({marks})",
                part,
            ):
                found[row[0]] = row
        missing = [i for i in ids if i not in found]
        if missing:
            raise DatabaseError(self.path, f"no scan with id {missing[0]}")
        nfeat = int(np.prod(self.feature_shape))
        poses = np.full((len(ids), 4), np.nan)
        scales = np.empty(len(ids), dtype=np.float32)
        paths, blobs = [], []
        for k, i in enumerate(ids):
            _, path, x, y, z, yaw, blob, scale = found[i]
            if len(blob) != nfeat * _FEAT_DTYPE.itemsize:
                raise DatabaseError(self.path, f"scan {i}: features have a wrong size")
            if not (isinstance(scale, float) and np.isfinite(scale) and scale > 0):
                raise DatabaseError(self.path, f"scan {i}: bad feature scale {scale!r}")
            blobs.append(blob)
            scales[k] = scale
            poses[k] = [np.nan if v is None else v for v in (x, y, z, yaw)]
            paths.append(path)
        # All rows decoded at once and scaled in float32: a float16 product per row was
        # most of a query's time (NumPy's mixed float16 loops are slow), rounded to
        # float16, and overflowed past 65504.
        stored = np.frombuffer(b"".join(blobs), dtype=_FEAT_DTYPE).reshape(len(ids), nfeat)
        feats = stored.astype(np.float32)
        with np.errstate(over="ignore", invalid="ignore"):
            feats *= scales[:, None]
        bad = ~np.isfinite(feats).all(axis=1)
        if bad.any():
            i = ids[int(np.argmax(bad))]
            raise DatabaseError(self.path, f"scan {i}: features are not finite (damaged?)")
        feats = feats.reshape(len(ids), *self.feature_shape)
        return MatchRows(np.asarray(ids, dtype=np.int64), paths, poses, feats)

    @_sql_errors
    def existing(self, paths: Iterable[str]) -> set[str]:
        """Which of `paths` are stored already (for resuming a build)."""
        stored = set(r[0] for r in self._conn.execute("SELECT path FROM scans"))
        return {p for p in paths if p in stored}

    def size_bytes(self) -> int:
        total = 0
        for suffix in ("", "-wal", "-shm"):
            p = Path(str(self.path) + suffix)
            if p.exists():
                total += p.stat().st_size
        return total

    @_sql_errors
    def check(self) -> list[str]:
        """`PRAGMA integrity_check` plus the size and finiteness of every blob; problems found."""
        problems = [r[0] for r in self._conn.execute("PRAGMA integrity_check") if r[0] != "ok"]
        nsig = self.signature_dim * _SIG_DTYPE.itemsize
        nfeat = int(np.prod(self.feature_shape)) * _FEAT_DTYPE.itemsize
        cur = self._conn.execute(
            "SELECT id, path, signature, features, feature_scale FROM scans ORDER BY id"
        )
        for rid, path, sig, feat, scale in cur:
            if not isinstance(sig, bytes) or len(sig) != nsig:
                problems.append(f"scan {rid} ({path}): signature is not {nsig} bytes")
            elif not np.isfinite(np.frombuffer(sig, dtype=_SIG_DTYPE)).all():
                problems.append(f"scan {rid} ({path}): signature is not finite")
            if not isinstance(feat, bytes) or len(feat) != nfeat:
                problems.append(f"scan {rid} ({path}): features are not {nfeat} bytes")
            elif not np.isfinite(np.frombuffer(feat, dtype=_FEAT_DTYPE)).all():
                problems.append(f"scan {rid} ({path}): features are not finite")
            if not (isinstance(scale, float) and np.isfinite(scale) and scale > 0):
                problems.append(f"scan {rid} ({path}): bad feature scale {scale!r}")
        if self.side_offsets:
            counts = dict(
                self._conn.execute("SELECT scan_id, COUNT(*) FROM side_views GROUP BY scan_id")
            )
            for rid, sig in self._conn.execute("SELECT scan_id, signature FROM side_views"):
                if not isinstance(sig, bytes) or len(sig) != nsig:
                    problems.append(f"scan {rid}: a side view is not {nsig} bytes")
                elif not np.isfinite(np.frombuffer(sig, dtype=_SIG_DTYPE)).all():
                    problems.append(f"scan {rid}: a side view is not finite")
            lacking = len(self) - sum(1 for c in counts.values() if c == len(self.side_offsets))
            if lacking:
                problems.append(f"{lacking} scans lack some of their side views")
        return problems


def _first_damaged(ids: np.ndarray, sigs: np.ndarray) -> int | None:
    """The id of the first signature that would derail the search (NaN, or so large that
    its squared norm overflows float32), or None."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.einsum("ij,ij->i", sigs, sigs, dtype=np.float64)
    bad = ~(np.isfinite(norms) & (norms < np.finfo(np.float32).max))
    return int(ids[np.argmax(bad)]) if bad.any() else None


def _locate(
    stored: str, rel: str | None, db_path: Path, scan_root: str | Path | None
) -> Path | None:
    """The resolution order of `Database.locate`. A scan in a ROS bag
    (`BAG#TOPIC@STAMP_NS`) exists when its bag does."""
    from disco_cli.readers import is_bag_message

    def exists(p: Path) -> bool:
        return p.exists() or is_bag_message(p)

    first = Path(stored)
    if exists(first):
        return first if first.is_absolute() else Path(os.path.abspath(first))
    if rel:
        beside = Path(os.path.abspath(db_path)).parent / rel
        if exists(beside):
            return Path(os.path.normpath(beside))
    if scan_root is not None:
        parts = [p for p in first.parts if p not in (first.anchor, "..", ".")]
        for k in range(len(parts)):
            candidate = Path(scan_root, *parts[k:])
            if exists(candidate):
                return Path(os.path.abspath(candidate))
    return None


def stored_paths(paths: Sequence[str], db_path: str | Path) -> tuple[list[str], list[str | None]]:
    """What a database at `db_path` stores for scans given as `paths`: the absolute
    path, and the path relative to the database's folder (None where there is none,
    e.g. on another Windows drive)."""
    folder = os.path.dirname(os.path.abspath(db_path))
    absolute = [os.path.abspath(p) for p in paths]
    rel: list[str | None] = []
    for p in absolute:
        try:
            rel.append(os.path.relpath(p, folder))
        except ValueError:
            rel.append(None)
    return absolute, rel


def _check_header(path: Path) -> None:
    """The SQLite magic, the page size, and a file size that is whole pages and at least
    what the header says: a file cut anywhere (by a full disk, a copy that stopped, a
    download) is named as cut here, before SQLite reads it."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(_HEADER_SIZE)
    except OSError as exc:
        raise DatabaseError(path, f"cannot read ({exc.strerror or exc})") from None
    if not head:
        raise DatabaseError(path, "empty file, not a disco database")
    if head[: len(_SQLITE_MAGIC)] != _SQLITE_MAGIC:
        if len(head) < len(_SQLITE_MAGIC) and _SQLITE_MAGIC.startswith(head):
            raise DatabaseError(path, f"truncated: {size} bytes, shorter than the SQLite header")
        raise DatabaseError(path, "not a disco database (not an SQLite file)")
    if len(head) < _HEADER_SIZE:
        raise DatabaseError(path, f"truncated: {size} bytes, shorter than the SQLite header")
    page_size = int.from_bytes(head[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    if page_size < 512 or page_size & (page_size - 1):
        raise DatabaseError(path, f"corrupt database: bad page size {page_size} in its header")
    if size % page_size:
        raise DatabaseError(
            path,
            f"truncated or damaged: {size} bytes is not a whole number of {page_size}-byte pages",
        )
    # The page count in the header counts only when its change counter agrees (SQLite's
    # own rule), and the file itself is then the whole database unless a WAL holds more.
    pages = int.from_bytes(head[28:32], "big")
    valid = pages > 0 and head[24:28] == head[92:96]
    wal = Path(f"{path}-wal")
    wal_pending = wal.is_file() and wal.stat().st_size > 0
    if valid and not wal_pending and size < pages * page_size:
        raise DatabaseError(
            path,
            f"truncated: {size} bytes, but its header says {pages} pages of {page_size} bytes "
            f"({pages * page_size} bytes)",
        )


def _check_integrity(path: Path, conn: sqlite3.Connection) -> None:
    """SQLite's integrity check over the whole file; `DatabaseError` with the first few
    problems on one line when it finds any."""
    try:
        rows = conn.execute(f"PRAGMA integrity_check({_PROBLEMS_SHOWN + 1})").fetchall()
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(path, f"corrupt database ({exc})") from None
    # SQLite may pack several problems into one row, one per line, under a heading.
    problems = [
        " ".join(line.split())
        for r in rows
        if r and r[0] != "ok"
        for line in str(r[0]).splitlines()
        if line.strip() and not line.startswith("***")
    ]
    if problems:
        shown = "; ".join(problems[:_PROBLEMS_SHOWN])
        more = ", ..." if len(problems) > _PROBLEMS_SHOWN else ""
        raise DatabaseError(path, f"corrupt database (integrity check: {shown}{more})")


def _connect(path: Path, writable: bool) -> sqlite3.Connection:
    mode = "rw" if writable or os.access(path, os.W_OK) else "ro"
    try:
        conn = sqlite3.connect(f"file:{path}?mode={mode}", uri=True, timeout=30.0)
        conn.execute("PRAGMA busy_timeout=30000")
    except sqlite3.Error as exc:
        raise DatabaseError(path, f"cannot open ({exc})") from None
    return conn


def _read_meta(path: Path, conn: sqlite3.Connection) -> dict[str, str]:
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(path, f"corrupt or not an SQLite database ({exc})") from None
    if "meta" not in tables or "scans" not in tables:
        raise DatabaseError(path, "not a disco database (no meta/scans tables)")
    try:
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(path, f"corrupt database ({exc})") from None
    if "format_version" not in meta:
        raise DatabaseError(path, "not a disco database (no format version)")
    try:
        version = int(meta["format_version"])
    except ValueError:
        raise DatabaseError(path, f"bad format version {meta['format_version']!r}") from None
    if version > FORMAT_VERSION:
        raise DatabaseError(
            path,
            f"database format version {version} is newer than this disco supports "
            f"({FORMAT_VERSION}); upgrade disco",
        )
    needed = (
        "model_name",
        "fingerprint",
        "model_config",
        "bev_config",
        "signature_dim",
        "feature_shape",
    )
    missing = [k for k in needed if k not in meta]
    if missing:
        raise DatabaseError(path, f"corrupt database: meta lacks {', '.join(missing)}")
    try:
        json.loads(meta["model_config"]), json.loads(meta["bev_config"])
        json.loads(meta["feature_shape"]), int(meta["signature_dim"])
    except (ValueError, TypeError):
        raise DatabaseError(path, "corrupt database: unreadable meta values") from None
    return meta


def _check_scans_table(path: Path, conn: sqlite3.Connection) -> None:
    try:
        cols = {r[1] for r in conn.execute("PRAGMA table_info(scans)")}
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(path, f"corrupt database ({exc})") from None
    missing = _SCAN_COLUMNS - cols
    if missing:
        lacks = ", ".join(sorted(missing))
        raise DatabaseError(path, f"not a disco database (scans lacks {lacks})")
