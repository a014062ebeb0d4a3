"""The map database: one SQLite file (WAL journal) of scan signatures, features and poses.

Layout (format version 2; docs/database.md has the tables and the figures):

- `meta(key, value)`: `format_version`, `disco_version`, `model_name`, `fingerprint`,
  `model_config` and `bev_config` (JSON), `signature_dim`, `feature_shape` (JSON),
  `feature_dtype`, `feature_codec`, `generation` (bumped by every write).
- `scans(id, path, rel_path, time, x, y, z, yaw, signature, signature_scale, crc)`: one
  row per scan, `id` in insertion order (1, 2, ...), `path` absolute and unique,
  `rel_path` relative to the database's folder (NULL where there is none), time and
  pose NULL when unknown, `signature` float16 little-endian divided by
  `signature_scale` (its largest magnitude).
- `features(id, scale, data, crc)`: the scan's feature images as float16 divided by
  `scale`, deflated (zlib, raw stream): read only for the rows a query re-ranks.
- `side_views(scan_id, offset_m, signature, signature_scale, crc)`: only in a map built
  with side views (meta `side_views_m`): each scan's signatures re-centred `offset_m`
  to its side (`side_views.py`), searched beside the scans'.

Every row carries `crc`, the CRC-32 of its payload (its id and every other column, in a
fixed byte layout: `_scan_crc`, `_feature_crc`, `_view_crc`), written with the row and
checked whenever the row is read. A row whose checksum or values fail is *damaged*:
reads skip it and record it in `Database.damaged`; `rows()` raises `DamagedRows`, so
that nothing uses it silently; `check()` lists every one (`disco info --check`), and
`rewrite()` replaces them (`disco build-db --repair`).

Format 1 (before checksums: float32 signatures and raw float16 features in `scans`)
is read as it is, unverified; opening one for writing first migrates it to format 2
(`migrate`), writing a new file and renaming it into place, and keeps the original file
beside it as `map.db.v1` (the conversion rounds float32 to float16).

Every append is one transaction, so a crash or Ctrl-C leaves every finished batch and
nothing half-written; readers opened meanwhile see a consistent state (WAL). A new
database is written to a hidden temporary file and renamed into place only when its
first batch is committed, so no half-initialized file is ever left at the target.

Opening is cheap: the SQLite header and the file's size (a cut file is named as such),
the meta table and the schema; what a command then reads is verified row by row.
SQLite's full `PRAGMA integrity_check` (every page, every b-tree, the index) runs
before any write, and in `check()` (`disco info --check`). A damaged file is refused
with one `DatabaseError` naming it and the problem, and is left byte for byte as it
was; any SQLite error met later is turned into a `DatabaseError` too, never passed on
as `sqlite3.DatabaseError`, and a permission problem is never called damage. A map this
process may not write (its file or folder) opens read-only (`mode=ro`, or
`immutable=1` where SQLite cannot put the WAL's -shm file beside it), with one note.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import sqlite3
import stat
import struct
import sys
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote

import numpy as np

from disco_cli.errors import DatabaseError

__all__ = [
    "FORMAT_VERSION",
    "Database",
    "DamagedRows",
    "ModelInfo",
    "ScanBatch",
    "MatchRows",
    "stored_paths",
]

FORMAT_VERSION = 2
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER_SIZE = 100
# At most this many problems of the integrity check are named in the error line.
_PROBLEMS_SHOWN = 3
_SIG_DTYPE = np.dtype("<f2")
_SIG_DTYPE_V1 = np.dtype("<f4")
_FEAT_DTYPE = np.dtype("<f2")
# Large pages keep a row's blobs in its b-tree leaf: no half-empty overflow page per
# row (about 2 KiB of a 4 KiB page's worth); ~7 feature rows and ~30 scan rows a page.
_PAGE_SIZE = 65536
# zlib level 6: 39 % of the float16 bytes on the samples; deflating is only at writing.
_DEFLATE_LEVEL = 6
# Features keep 9 significant bits of float16's 11 (rounded to nearest: a relative error
# <= 2^-9); docs/database.md has what that costs in yaw and matches.
_FEATURE_DROP_BITS = 2
_NOT_FINITE = "features are not finite"
# Decoded feature rows `Database.rows` keeps (about 38 KB each for the default model).
_CACHED_ROWS = 256
# How many damaged scans a warning names before "and N more".
_NAMED = 20

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE scans (
    id INTEGER PRIMARY KEY,
    path TEXT NOT NULL UNIQUE,
    rel_path TEXT,
    time REAL,
    x REAL, y REAL, z REAL, yaw REAL,
    signature BLOB NOT NULL,
    signature_scale REAL NOT NULL,
    crc INTEGER NOT NULL
);
CREATE TABLE features (
    id INTEGER PRIMARY KEY,
    scale REAL NOT NULL,
    data BLOB NOT NULL,
    crc INTEGER NOT NULL
);
"""
_SIDE_SCHEMA = """
CREATE TABLE side_views (
    scan_id INTEGER NOT NULL,
    offset_m REAL NOT NULL,
    signature BLOB NOT NULL,
    signature_scale REAL NOT NULL,
    crc INTEGER NOT NULL,
    PRIMARY KEY (scan_id, offset_m)
)
"""
_SIDE_SCHEMA_V1 = """
CREATE TABLE side_views (
    scan_id INTEGER NOT NULL,
    offset_m REAL NOT NULL,
    signature BLOB NOT NULL,
    PRIMARY KEY (scan_id, offset_m)
)
"""
_SCAN_COLUMNS = {
    1: {"id", "path", "time", "x", "y", "z", "yaw", "signature", "features", "feature_scale"},
    2: {"id", "path", "rel_path", "time", "x", "y", "z", "yaw", "signature", "signature_scale"},
}
# One scan row as stored and checksummed: id, path, rel_path, time, x, y, z, yaw,
# signature, signature_scale, crc.
_SCAN_ROW = "id, path, rel_path, time, x, y, z, yaw, signature, signature_scale, crc"


def _f64(v: Any) -> float:
    return np.nan if v is None else float(v)


def _scan_crc(
    rid: int,
    path: str,
    rel: str | None,
    time: Any,
    x: Any,
    y: Any,
    z: Any,
    yaw: Any,
    sig: bytes,
    sig_scale: Any,
) -> int:
    """CRC-32 of a scan row's payload. NULL reals count as NaN, a NULL rel_path as one
    0xFF byte (no UTF-8 text is that), so every stored value changes the checksum."""
    nan = np.nan
    head = struct.pack(
        "<q6d",
        rid,
        nan if time is None else time,
        nan if x is None else x,
        nan if y is None else y,
        nan if z is None else z,
        nan if yaw is None else yaw,
        nan if sig_scale is None else sig_scale,
    )
    text = path.encode("utf-8", "surrogateescape") + b"\x00"
    text += b"\xff" if rel is None else rel.encode("utf-8", "surrogateescape")
    return zlib.crc32(sig, zlib.crc32(text, zlib.crc32(head)))


def _feature_crc(rid: int, scale: Any, data: bytes) -> int:
    return zlib.crc32(data, zlib.crc32(struct.pack("<qd", rid, _f64(scale))))


def _view_crc(rid: int, offset: Any, sig: bytes, sig_scale: Any) -> int:
    head = struct.pack("<q2d", rid, _f64(offset), _f64(sig_scale))
    return zlib.crc32(sig, zlib.crc32(head))


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


def _scaled(v: np.ndarray, dtype: np.dtype) -> tuple[bytes, float]:
    """`v` divided by its largest magnitude (1 if all zero), as `dtype` bytes: float16
    then neither overflows (65504) nor flushes small values to zero."""
    scale = float(np.max(np.abs(v))) if v.size else 0.0
    if not np.isfinite(scale):
        raise ValueError("values are not finite")
    if scale == 0.0:
        scale = 1.0
    return (v / scale).astype(dtype).tobytes(), scale


def _encode_features(f: np.ndarray) -> tuple[bytes, float]:
    raw, scale = _scaled(f, _FEAT_DTYPE)
    # Round away the float16's lowest mantissa bits (to nearest, in the bit pattern,
    # which orders magnitudes; values are <= 1 here, far from the infinities): the
    # deflated blob shrinks by about 11 % (real KITTI scans: 9.9 -> 8.8 KB).
    step = 1 << _FEATURE_DROP_BITS
    bits = np.frombuffer(raw, dtype="<u2")
    raw = ((bits + np.uint16(step >> 1)) & np.uint16(0xFFFF ^ (step - 1))).astype("<u2").tobytes()
    packer = zlib.compressobj(_DEFLATE_LEVEL, zlib.DEFLATED, -15)  # raw: the crc is ours
    return packer.compress(raw) + packer.flush(), scale


class DamagedRows(DatabaseError):
    """Rows asked for by `Database.rows` that fail their checksum or values: `ids`."""

    def __init__(self, path: Path, damaged: dict[int, str]):
        self.ids = sorted(damaged)
        super().__init__(path, damaged_line(damaged, path))


def damaged_line(damaged: dict[int, str], path: Any) -> str:
    """One line naming damaged scans (`{id: what}`) and the way out."""
    named = ", ".join(f"scan {i} ({damaged[i]})" for i in sorted(damaged)[:_NAMED])
    more = f" and {len(damaged) - _NAMED} more" if len(damaged) > _NAMED else ""
    rows = "row" if len(damaged) == 1 else "rows"
    return (
        f"{len(damaged)} damaged {rows} skipped: {named}{more}; `disco info --check` "
        "lists them, `disco build-db SCANS -o MAP --repair` rewrites them"
    )


_F = TypeVar("_F", bound=Callable[..., Any])


def _sql_errors(func: _F) -> _F:
    """Turn an SQLite error met while reading or writing into one `DatabaseError`
    naming the file: a page that turns out damaged only when it is read, a disk error."""

    @functools.wraps(func)
    def wrapper(self: Database, *args: Any, **kwargs: Any) -> Any:
        try:
            return func(self, *args, **kwargs)
        except sqlite3.DatabaseError as exc:
            raise _sqlite_error(self.path, exc, "corrupt or unreadable database") from None

    return wrapper  # type: ignore[return-value]


class Database:
    """An open map database. Use `Database.open(path)` or `Database.create(path, ...)`.

    `damaged` maps the id of every scan whose row (or one of its rows: features, a side
    view) was found damaged by a read so far to what names it (its stored path); `check()`
    fills it for the whole file."""

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
        self.damaged: dict[int, str] = {}
        # rows(): the last rows read, decoded (id -> path, pose, features), valid while
        # the file's generation is the one they were read at.
        self._cache: OrderedDict[int, tuple] = OrderedDict()
        self._cache_generation: int | None = None
        # Stored sizes of one signature and one (decompressed) feature block.
        sig_dtype = _SIG_DTYPE if self.format_version >= 2 else _SIG_DTYPE_V1
        self._nsig = self.signature_dim * sig_dtype.itemsize
        self._nfeat = int(np.prod(self.feature_shape)) * _FEAT_DTYPE.itemsize
        # (bytes before, bytes after) when opening for writing migrated a format-1 file,
        # and where the original was kept.
        self.migrated: tuple[int, int] | None = None
        self.migration_backup: Path | None = None
        # Why the map was opened read-only (its file or folder is not writable here:
        # the note `open` gives), or None.
        self.read_only: str | None = None
        try:
            columns = {r[1] for r in conn.execute("PRAGMA table_info(scans)")}
        except sqlite3.DatabaseError as exc:
            raise _sqlite_error(path, exc, "corrupt or unreadable database") from None
        # Databases written before relative paths were stored lack the column.
        self._has_rel = "rel_path" in columns
        try:
            offsets = json.loads(meta.get("side_views_m", "[]"))
            self.side_offsets: tuple[float, ...] = tuple(float(o) for o in offsets)
        except (ValueError, TypeError):
            raise DatabaseError(path, "corrupt database: unreadable side_views_m") from None
        try:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
        except sqlite3.DatabaseError as exc:
            raise _sqlite_error(path, exc, "corrupt or unreadable database") from None
        if self.side_offsets and "side_views" not in tables:
            raise DatabaseError(path, "corrupt database: side views named but not stored")
        if self.checksummed and "features" not in tables:
            raise DatabaseError(path, "corrupt database: no features table")

    @property
    def checksummed(self) -> bool:
        """Whether rows carry checksums (format 2); a format-1 map's rows are unverified."""
        return self.format_version >= 2

    # -- opening --------------------------------------------------------------

    @classmethod
    def open(
        cls,
        path: str | Path,
        writable: bool = False,
        verify: bool = False,
        on_note: Callable[[str], None] | None = None,
    ) -> Database:
        """Open an existing database; raise `DatabaseError` naming the problem otherwise.

        Opening reads the header, the meta table and the schema: its cost does not grow
        with the map. Every row is verified when it is read (its checksum), so damage
        inside what a command reads is still found; SQLite's full `PRAGMA
        integrity_check` (every page, about 12-18 ms per 1,000 scans from the page
        cache) runs only with `verify=True`, for writing (a write onto a damaged b-tree
        can spread the damage), and in `check()` (`disco info --check`). A refused file
        is not modified.

        A map this process may not write (its file or folder; a read-only volume) opens
        read-only, and `on_note` hears one line saying so (default: `note: ...` on
        stderr); `read_only` holds it. Opening a format-1 file for writing migrates it to
        format 2 and keeps the original beside it (`migrated`, `migrated_line()`).
        """
        path = Path(path)
        db = cls._open(path, writable, verify)
        if writable and db.format_version < FORMAT_VERSION:
            db.close()
            before, after, backup = _migrate(path)
            db = cls._open(path, writable, verify)
            db.migrated = (before, after)
            db.migration_backup = backup
        if db.read_only is not None:
            (on_note or _note_on_stderr)(f"{path}: {db.read_only}")
        return db

    @classmethod
    def _open(cls, path: Path, writable: bool, verify: bool) -> Database:
        try:
            st = path.stat()
        except FileNotFoundError:
            raise DatabaseError(path, "no such database") from None
        except OSError as exc:
            raise DatabaseError(path, f"cannot read ({exc.strerror or exc})") from None
        if not stat.S_ISREG(st.st_mode):
            raise DatabaseError(path, "not a file")
        _check_header(path)
        conn, read_only = _connect(path, writable)
        try:
            if verify or writable:
                _check_integrity(path, conn)
            meta = _read_meta(path, conn)
            _check_scans_table(path, conn, int(meta["format_version"]))
            if writable and int(meta["format_version"]) >= 2:
                conn.execute("PRAGMA journal_mode=WAL")
            db = cls(path, conn, meta)
            db.read_only = read_only
            return db
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise _sqlite_error(path, exc, "corrupt or unreadable database") from None
        except BaseException:
            conn.close()
            raise

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
            "disco_version": disco_version,
            "model_name": model.name,
            "fingerprint": model.fingerprint,
            "model_config": json.dumps(model.model_config, sort_keys=True),
            "bev_config": json.dumps(model.bev_config, sort_keys=True),
            "signature_dim": str(first.signatures.shape[1]),
            "feature_shape": json.dumps(list(first.features.shape[1:])),
            **(extra_meta or {}),
        }
        if first.side_offsets:
            meta["side_views_m"] = json.dumps(list(first.side_offsets))
        try:
            tmp.unlink(missing_ok=True)
            conn = _new_file(tmp, meta, bool(first.side_offsets))
            try:
                cls(path, conn, _read_meta(tmp, conn)).append(first)
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

    def migrated_line(self) -> str:
        """What opening this map migrated, as one line ('' if nothing)."""
        if self.migrated is None:
            return ""
        before, after = self.migrated
        return (
            f"{self.path}: migrated from format 1 to format 2 (checksummed rows; signatures "
            f"rounded to float16): {before} -> {after} bytes; the format-1 file is kept as "
            f"{self.migration_backup}"
        )

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
                f"pass --model {self.meta.get('model_source') or mine.name} (or no --model: "
                "a map's own model is the default), or build a new database",
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
    def append(self, batch: ScanBatch) -> list[int]:
        """Append one batch of scans in one transaction (all or nothing); their ids.

        Nothing here grows with the map: the next id is the rowid b-tree's last key, and
        the only index is the one on `path` (a b-tree insert)."""
        if not batch.paths:
            return []
        self._check_writable_format()
        self.check_batch_shapes(batch)
        encoded = _encode_batch(batch)
        with self._write_transaction("append"):
            last = self._conn.execute("SELECT MAX(id) FROM scans").fetchone()[0] or 0
            ids = list(range(last + 1, last + 1 + len(batch.paths)))
            _insert_rows(self._conn, ids, batch, encoded)
        return ids

    @_sql_errors
    def rewrite(self, ids: Sequence[int], batch: ScanBatch) -> None:
        """Replace the stored rows of the scans `ids` (features and side views included)
        with `batch`, in one transaction: `disco build-db --repair`'s write."""
        ids = [int(i) for i in ids]
        if len(ids) != len(batch.paths):
            raise ValueError(f"{len(ids)} ids for {len(batch.paths)} scans")
        if not ids:
            return
        self._check_writable_format()
        self.check_batch_shapes(batch)
        encoded = _encode_batch(batch)
        marks = ",".join("?" * len(ids))
        with self._write_transaction("rewrite"):
            for table, key in (("scans", "id"), ("features", "id"), ("side_views", "scan_id")):
                if table != "side_views" or self.side_offsets:
                    self._conn.execute(f"DELETE FROM {table} WHERE {key} IN ({marks})", ids)
            _insert_rows(self._conn, ids, batch, encoded)
        for i in ids:
            self.damaged.pop(i, None)

    def _check_writable_format(self) -> None:
        if not self.checksummed:
            raise DatabaseError(
                self.path, "format 1 map opened read-only; open it for writing to migrate it"
            )

    @contextmanager
    def _write_transaction(self, what: str) -> Iterator[None]:
        """One write transaction (all or nothing) that raises the map's `generation`;
        SQLite's errors become one `DatabaseError` ("cannot <what>: ...")."""
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield
                self._bump_generation()
                self._conn.commit()
            except BaseException:
                self._conn.rollback()
                raise
        except sqlite3.IntegrityError as exc:
            raise DatabaseError(self.path, f"cannot {what}: {exc}") from None
        except sqlite3.Error as exc:
            raise DatabaseError(self.path, f"cannot write: {exc}") from None

    def _bump_generation(self) -> None:
        self._conn.execute(
            "UPDATE meta SET value = CAST(CAST(value AS INTEGER) + 1 AS TEXT) "
            "WHERE key = 'generation'"
        )

    # -- reading ----------------------------------------------------------------

    @property
    @_sql_errors
    def generation(self) -> int:
        """A number that changes with every write (append, repair, migration): a cheap
        key for anything derived from the map (an index file beside it) to know it is
        stale. Read from the file each time, so another process's appends count. A
        format-1 map (append-only, no counter) answers its largest id."""
        if self.checksummed:
            row = self._conn.execute("SELECT value FROM meta WHERE key = 'generation'").fetchone()
            try:
                return int(row[0])
            except (TypeError, ValueError):
                raise DatabaseError(self.path, "corrupt database: bad generation") from None
        return int(self._conn.execute("SELECT MAX(id) FROM scans").fetchone()[0] or 0)

    @_sql_errors
    def __len__(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM scans").fetchone()[0])

    @_sql_errors
    def next_id(self) -> int:
        """The id the next appended scan gets (ids are never reused)."""
        return int(self._conn.execute("SELECT MAX(id) FROM scans").fetchone()[0] or 0) + 1

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
    def ids(self) -> np.ndarray:
        """Every stored id, in order (the rows of `paths()`, `poses()`, `locations()`)."""
        rows = self._conn.execute("SELECT id FROM scans ORDER BY id").fetchall()
        return np.array([r[0] for r in rows], dtype=np.int64)

    @_sql_errors
    def stored_names(self, ids: Iterable[int]) -> dict[int, tuple[str, str | None]]:
        """`{id: (path, rel_path)}` as stored, unverified (what a damaged row says it is)."""
        column = "rel_path" if self._has_rel else "NULL"
        out = {}
        for i in ids:
            row = self._conn.execute(
                f"SELECT path, {column} FROM scans WHERE id = ?", (int(i),)
            ).fetchone()
            if row is not None:
                out[int(i)] = (row[0], row[1])
        return out

    @_sql_errors
    def has_poses(self) -> bool:
        row = self._conn.execute("SELECT 1 FROM scans WHERE x IS NOT NULL LIMIT 1").fetchone()
        return row is not None

    def _scan_query(self) -> str:
        """The scan rows' columns that their checksum covers (format 1: what there is)."""
        if self.checksummed:
            return f"SELECT {_SCAN_ROW} FROM scans"
        rel = "rel_path" if self._has_rel else "NULL"
        return f"SELECT id, path, {rel}, time, x, y, z, yaw, signature, 1.0, NULL FROM scans"

    def _sound_scans(self, rows: list[tuple]) -> tuple[list[tuple], np.ndarray, dict[int, str]]:
        """Of scan rows (`_scan_query`), the sound ones, their signatures `[K, D]` float32,
        and `{id: problem}` of the others: the checks every read and `check()` share."""
        sound, blobs, scales, bad = [], [], [], {}
        for row in rows:
            problem = self._scan_problem(row)
            if problem:
                bad[row[0]] = problem
            else:
                sound.append(row)
                blobs.append(row[8])
                scales.append(row[9])
        dtype = _SIG_DTYPE if self.checksummed else _SIG_DTYPE_V1
        sigs = np.frombuffer(b"".join(blobs), dtype=dtype).reshape(len(sound), self.signature_dim)
        sigs = sigs.astype(np.float32)
        if self.checksummed:
            sigs *= np.asarray(scales, dtype=np.float32)[:, None]
        out_of_range = _bad_signatures(sigs)
        if out_of_range.any():
            for k in np.flatnonzero(out_of_range):
                bad[sound[k][0]] = "signature is not finite or out of range"
            keep = ~out_of_range
            sound = [r for r, k in zip(sound, keep) if k]
            sigs = sigs[keep]
        return sound, sigs, bad

    def _scan_problem(self, row: tuple) -> str | None:
        rid, path, rel, t, x, y, z, yaw, sig, sig_scale, crc = row
        if not isinstance(sig, bytes) or len(sig) != self._nsig:
            return f"signature is not {self._nsig} bytes"
        if not isinstance(path, str) or not (rel is None or isinstance(rel, str)):
            return "path is not text"
        for v in (t, x, y, z, yaw, sig_scale):
            if v is not None and type(v) is not float and type(v) is not int:
                return "time or pose is not a number"
        if not self.checksummed:
            return None
        if crc != _scan_crc(rid, path, rel, t, x, y, z, yaw, sig, sig_scale):
            return "checksum mismatch (signature, pose, time or path changed)"
        if not (sig_scale is not None and np.isfinite(sig_scale) and sig_scale > 0):
            return f"bad signature scale {sig_scale!r}"
        return None

    def _note_damaged(self, bad: dict[int, str], names: dict[int, str]) -> None:
        for rid in bad:
            self.damaged[int(rid)] = names.get(rid, "?")

    @_sql_errors
    def signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(ids [N] int64, signatures [N, D] float32)` of the sound scans, in id order.

        Every row is verified (checksum, size, values that would derail the search: NaN,
        or so large that the squared norm overflows float32); a damaged one is left out
        and recorded in `damaged`. An empty map, or one with no sound scan, is refused."""
        n = len(self)
        if n == 0:
            raise DatabaseError(self.path, "the database is empty")
        ids = np.empty(n, dtype=np.int64)
        sigs = np.empty((n, self.signature_dim), dtype=np.float32)
        cur = self._conn.execute(self._scan_query() + " ORDER BY id")
        i = seen = 0
        while rows := cur.fetchmany(4096):
            rows = rows[: n - seen]  # rows appended since the count: not in this snapshot
            seen += len(rows)
            sound, part, bad = self._sound_scans(rows)
            self._note_damaged(bad, {r[0]: r[1] for r in rows})
            ids[i : i + len(sound)] = [r[0] for r in sound]
            sigs[i : i + len(sound)] = part
            i += len(sound)
            if len(rows) < 4096:
                break
        if i == 0:
            raise DatabaseError(
                self.path, "no sound scan: " + damaged_line(self.damaged, self.path)
            )
        return ids[:i], sigs[:i]

    @_sql_errors
    def side_signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(scan ids [M], signatures [M, D])` of the sound stored side views (none: empty);
        a damaged view is left out and its scan recorded in `damaged`."""
        if not self.side_offsets:
            return np.empty(0, np.int64), np.empty((0, self.signature_dim), np.float32)
        ids, sigs, bad = self._sound_views(self._views())
        self._note_damaged(bad, {i: "a side view" for i in bad})
        return ids, sigs

    def _views(self) -> list[tuple]:
        if self.checksummed:
            query = "SELECT scan_id, offset_m, signature, signature_scale, crc FROM side_views"
        else:
            query = "SELECT scan_id, offset_m, signature, 1.0, NULL FROM side_views"
        return self._conn.execute(query + " ORDER BY scan_id, offset_m").fetchall()

    def _sound_views(self, rows: list[tuple]) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
        sound, bad = [], {}
        for row in rows:
            rid, offset, sig, sig_scale, crc = row
            if not isinstance(sig, bytes) or len(sig) != self._nsig:
                bad[rid] = f"a side view is not {self._nsig} bytes"
            elif self.checksummed and crc != _view_crc(rid, offset, sig, sig_scale):
                bad[rid] = "a side view fails its checksum"
            elif not isinstance(sig_scale, float) or not sig_scale > 0:
                bad[rid] = f"a side view has a bad scale {sig_scale!r}"
            else:
                sound.append(row)
        dtype = _SIG_DTYPE if self.checksummed else _SIG_DTYPE_V1
        blob = b"".join(r[2] for r in sound)
        sigs = np.frombuffer(blob, dtype=dtype).reshape(len(sound), self.signature_dim)
        sigs = sigs.astype(np.float32) * np.asarray([r[3] for r in sound], np.float32)[:, None]
        ids = np.asarray([r[0] for r in sound], dtype=np.int64)
        out_of_range = _bad_signatures(sigs)
        for k in np.flatnonzero(out_of_range):
            bad[int(ids[k])] = "a side view is not finite or out of range"
        return ids[~out_of_range], sigs[~out_of_range], bad

    @_sql_errors
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """`(poses [N, 4] x, y, z, yaw rad, times [N])` of every scan in id order, NaN where
        unknown, and where the row is damaged (recorded in `damaged`)."""
        rows = self._conn.execute(self._scan_query() + " ORDER BY id").fetchall()
        _, _, bad = self._sound_scans(rows)
        self._note_damaged(bad, {r[0]: r[1] for r in rows})
        unknown = (None,) * 5
        arr = np.array(
            [unknown if r[0] in bad else r[3:8] for r in rows], dtype=np.float64
        ).reshape(-1, 5)  # None -> nan
        return arr[:, 1:5], arr[:, 0]

    @_sql_errors
    def rows(self, ids: Sequence[int] | np.ndarray) -> MatchRows:
        """Paths, poses and features of the scans `ids`, in that order (only those rows).

        Every row read from the file is verified (its scan row and its features);
        damaged ones raise `DamagedRows` naming them (and are recorded in `damaged`): a
        caller that can go on without them leaves them out and asks again (`Map` does).
        The last `_CACHED_ROWS` rows read are kept decoded, while the file's
        `generation` stays the same: consecutive queries re-rank mostly the same
        neighbours, and inflating their features is most of a read's cost."""
        ids = [int(i) for i in np.asarray(ids).reshape(-1)]
        generation = self.generation
        if generation != self._cache_generation:
            self._cache.clear()
            self._cache_generation = generation
        todo = [i for i in dict.fromkeys(ids) if i not in self._cache]
        if todo:
            self._read_rows(todo)
        cache = self._cache
        for i in dict.fromkeys(ids):
            cache.move_to_end(i)
        entries = [cache[i] for i in ids]
        while len(cache) > max(_CACHED_ROWS, len(set(ids))):
            cache.popitem(last=False)
        feats = np.stack([e[2] for e in entries]) if entries else None
        if feats is None:
            feats = np.empty((0, *self.feature_shape), dtype=np.float32)
        poses = np.array([e[1] for e in entries], dtype=np.float64).reshape(-1, 4)
        return MatchRows(np.asarray(ids, dtype=np.int64), [e[0] for e in entries], poses, feats)

    def _read_rows(self, ids: list[int]) -> None:
        """Read, verify and decode the distinct rows `ids` into the cache, or raise
        `DamagedRows` for those that fail (nothing of this call is cached then)."""
        found: dict[int, tuple] = {}
        if self.checksummed:
            query = (
                f"SELECT {', '.join('s.' + c.strip() for c in _SCAN_ROW.split(','))}, "
                "f.scale, f.data, f.crc FROM scans s LEFT JOIN features f ON f.id = s.id "
                "WHERE s.id IN ({})"
            )
        else:
            rel = "rel_path" if self._has_rel else "NULL"
            query = (
                f"SELECT id, path, {rel}, time, x, y, z, yaw, signature, 1.0, NULL, "
                "feature_scale, features, NULL FROM scans WHERE id IN ({})"
            )
        for chunk in range(0, len(ids), 500):
            part = sorted(ids[chunk : chunk + 500])
            for row in self._conn.execute(query.format(",".join("?" * len(part))), part):
                found[row[0]] = row
        missing = [i for i in ids if i not in found]
        if missing:
            raise DatabaseError(self.path, f"no scan with id {missing[0]}")
        # Each row: its scan row's checksum (the signature is not decoded: it is not used
        # here), then its features' bytes; decoded together below.
        bad: dict[int, str] = {}
        raw: dict[int, tuple[bytes, float]] = {}
        for rid in ids:
            row = found[rid]
            problem = self._scan_problem(row[:11])
            data = None
            if problem is None:
                data, problem = self._feature_bytes(rid, *row[11:])
            if problem is not None:
                bad[rid] = problem
            else:
                raw[rid] = (data, row[11])  # type: ignore[assignment]
        order = list(raw)
        stored = np.frombuffer(b"".join(raw[i][0] for i in order), dtype=_FEAT_DTYPE)
        stored = stored.reshape(len(order), *self.feature_shape)
        scales = np.asarray([raw[i][1] for i in order], dtype=np.float32)
        with np.errstate(over="ignore", invalid="ignore"):
            decoded = stored.astype(np.float32)
            decoded *= scales.reshape(-1, *([1] * len(self.feature_shape)))
        size = int(np.prod(self.feature_shape))
        finite = np.isfinite(decoded.reshape(len(order), size)).all(axis=1)
        for k in np.flatnonzero(~finite):
            bad[order[k]] = _NOT_FINITE
        if bad:
            self._note_damaged(bad, {i: found[i][1] for i in bad})
            raise DamagedRows(self.path, {i: self.damaged[i] for i in bad})
        for k, rid in enumerate(order):
            row = found[rid]
            pose = tuple(np.nan if v is None else float(v) for v in row[4:8])
            self._cache[rid] = (row[1], pose, decoded[k])

    def _decoded_features(
        self, rid: int, scale: Any, data: Any, crc: Any
    ) -> tuple[np.ndarray | None, str | None]:
        """One scan's features `[...]` float32, or the problem that makes them unusable:
        `_feature_bytes`, then finite values (what `rows()` checks, there batched)."""
        raw, problem = self._feature_bytes(rid, scale, data, crc)
        if raw is None:
            return None, problem
        stored = np.frombuffer(raw, dtype=_FEAT_DTYPE).reshape(self.feature_shape)
        with np.errstate(over="ignore", invalid="ignore"):
            feats = stored.astype(np.float32) * np.float32(scale)
        if not np.isfinite(feats).all():
            return None, _NOT_FINITE
        return feats, None

    def _feature_bytes(
        self, rid: int, scale: Any, data: Any, crc: Any
    ) -> tuple[bytes | None, str | None]:
        """One scan's stored float16 feature bytes (checksum verified, inflated, sized,
        with a usable scale), or the problem."""
        if data is None:
            return None, "features are missing"
        if not isinstance(data, bytes):
            return None, "features are not a blob"
        if self.checksummed:
            if crc != _feature_crc(rid, scale, data):
                return None, "features fail their checksum"
            try:
                data = zlib.decompress(data, -15, self._nfeat)
            except zlib.error:
                return None, "features do not decompress"
        if len(data) != self._nfeat:
            return None, f"features are not {self._nfeat} bytes"
        if not (isinstance(scale, float) and np.isfinite(scale) and scale > 0):
            return None, f"bad feature scale {scale!r}"
        return data, None

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
        """Every problem of the file: `PRAGMA integrity_check`, then every row through the
        same checks as the reads a query makes (checksums, sizes, values), features and
        side views included. Fills `damaged` with every damaged scan."""
        problems = [r[0] for r in self._conn.execute("PRAGMA integrity_check") if r[0] != "ok"]
        self.damaged = {}
        names: dict[int, str] = {}
        bad: dict[int, str] = {}
        cur = self._conn.execute(self._scan_query() + " ORDER BY id")
        while rows := cur.fetchmany(4096):
            names.update((r[0], r[1]) for r in rows)
            bad.update(self._sound_scans(rows)[2])
        if self.checksummed:
            query = "SELECT id, scale, data, crc FROM features ORDER BY id"
        else:
            query = "SELECT id, feature_scale, features, NULL FROM scans ORDER BY id"
        with_features = set()
        for rid, scale, data, crc in self._conn.execute(query):
            with_features.add(rid)
            problem = self._decoded_features(rid, scale, data, crc)[1]
            if problem and rid not in bad:
                bad[rid] = problem
        for rid in set(names) - with_features:
            bad.setdefault(rid, "features are missing")
        for rid in with_features - set(names):
            problems.append(f"features of scan {rid}, which is not stored")
        if self.side_offsets:
            views = self._views()
            view_bad = self._sound_views(views)[2]
            for rid, problem in view_bad.items():
                bad.setdefault(rid, problem)
            counts: dict[int, int] = {}
            for v in views:
                counts[v[0]] = counts.get(v[0], 0) + 1
            lacking = [i for i in names if counts.get(i, 0) != len(self.side_offsets)]
            for rid in lacking:
                bad.setdefault(rid, "lacks some of its side views")
        for rid in sorted(bad):
            problems.append(f"scan {rid} ({names.get(rid, '?')}): {bad[rid]}")
        self._note_damaged(bad, names)
        return problems


def _bad_signatures(sigs: np.ndarray) -> np.ndarray:
    """Which signatures would derail the search (NaN, or so large that the squared norm
    overflows float32): the check every signature read and `check()` share."""
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.einsum("ij,ij->i", sigs, sigs, dtype=np.float64)
    return ~(np.isfinite(norms) & (norms < np.finfo(np.float32).max))


def _encode_batch(batch: ScanBatch) -> list[tuple]:
    """Each scan's stored blobs: (signature, its scale, features, their scale, views)."""
    out = []
    for i in range(len(batch.paths)):
        sig, sig_scale = _scaled(batch.signatures[i], _SIG_DTYPE)
        feats, scale = _encode_features(batch.features[i])
        views = [
            (float(o), *_scaled(batch.side_signatures[i, k], _SIG_DTYPE))  # type: ignore[index]
            for k, o in enumerate(batch.side_offsets)
        ]
        out.append((sig, sig_scale, feats, scale, views))
    return out


def _insert_rows(
    conn: sqlite3.Connection, ids: list[int], batch: ScanBatch, encoded: list[tuple]
) -> None:
    """Insert a batch's rows under `ids`, each with its checksum (inside the caller's
    transaction)."""
    scans, feats, views = [], [], []
    for k, rid in enumerate(ids):
        sig, sig_scale, data, scale, side = encoded[k]
        path, rel = str(batch.paths[k]), batch.rel_paths[k]  # type: ignore[index]
        t = _none_if_nan(batch.times[k])
        x, y, z, yaw = (_none_if_nan(v) for v in batch.poses[k])
        crc = _scan_crc(rid, path, rel, t, x, y, z, yaw, sig, sig_scale)
        scans.append((rid, path, rel, t, x, y, z, yaw, sig, sig_scale, crc))
        feats.append((rid, scale, data, _feature_crc(rid, scale, data)))
        for offset, vsig, vscale in side:
            views.append((rid, offset, vsig, vscale, _view_crc(rid, offset, vsig, vscale)))
    conn.executemany(f"INSERT INTO scans ({_SCAN_ROW}) VALUES ({', '.join('?' * 11)})", scans)
    conn.executemany("INSERT INTO features (id, scale, data, crc) VALUES (?, ?, ?, ?)", feats)
    if views:
        conn.executemany("INSERT INTO side_views VALUES (?, ?, ?, ?, ?)", views)


def _new_file(path: Path, meta: dict[str, str], side_views: bool) -> sqlite3.Connection:
    """A new, empty format-2 file at `path` with `meta` (plus the format's own keys)."""
    conn = sqlite3.connect(path)
    try:
        # Before any table: the page size of a file is fixed by its first write.
        conn.execute(f"PRAGMA page_size={_PAGE_SIZE}")
        meta = {
            **meta,
            "format_version": str(FORMAT_VERSION),
            "generation": "0",
            "signature_dtype": "float16",
            "feature_dtype": "float16",
            "feature_codec": "deflate",
        }
        with conn:
            for stmt in _SCHEMA.strip().split(";"):
                if stmt.strip():
                    conn.execute(stmt)
            if side_views:
                conn.execute(_SIDE_SCHEMA)
            conn.executemany("INSERT INTO meta VALUES (?, ?)", sorted(meta.items()))
    except BaseException:
        conn.close()
        raise
    return conn


def backup_path(path: str | Path) -> Path:
    """Where migrating the format-1 map at `path` keeps the original: `map.db.v1`."""
    path = Path(path)
    return path.with_name(f"{path.name}.v1")


def _migrate(path: Path) -> tuple[int, int, Path]:
    """Rewrite the format-1 map at `path` as format 2 (same ids, values and meta; rows
    checksummed as they are now) and rename it into place, keeping the original file as
    `backup_path(path)` (the conversion is lossy: float32 signatures become float16):
    (bytes before, after, the backup). A format-1 map with damaged rows is refused: it
    cannot be told what they were; so is one whose backup name is taken."""
    backup = backup_path(path)
    if os.path.lexists(backup):
        raise DatabaseError(
            path,
            f"cannot migrate from format 1: {backup} exists (the original of an earlier "
            "migration?) and would be replaced; move it away first",
        )
    # Fold a pending WAL into the file first, so that the file alone is the whole map
    # (the backup) and no WAL of the old file is left beside the new one. Without a
    # pending WAL the file is left byte for byte as it is.
    wal = Path(f"{path}-wal")
    if wal.is_file() and wal.stat().st_size > 0:
        conn = _connect(path, writable=True)[0]
        try:
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except sqlite3.Error as exc:
            raise DatabaseError(path, f"cannot migrate ({exc})") from None
        finally:
            conn.close()
    before = path.stat().st_size
    tmp = path.with_name(f".{path.name}.migrate-{os.getpid()}")
    old = Database._open(path, writable=False, verify=False)
    try:
        problems = old.check()
        if problems:
            raise DatabaseError(
                path,
                f"format 1 map with {len(problems)} problems ({problems[0]}); it cannot be "
                "migrated: rebuild it with disco build-db",
            )
        meta = {
            k: v
            for k, v in old.meta.items()
            if k not in ("format_version", "feature_dtype", "generation")
        }
        tmp.unlink(missing_ok=True)
        new = _new_file(tmp, meta, bool(old.side_offsets))
        try:
            views: dict[int, dict[float, np.ndarray]] = {}
            for rid, offset, sig, *_ in old._views() if old.side_offsets else []:
                views.setdefault(rid, {})[offset] = np.frombuffer(sig, _SIG_DTYPE_V1)
            ids = [r[0] for r in old._conn.execute("SELECT id FROM scans ORDER BY id")]
            for start in range(0, len(ids), 1000):
                part = old.rows(ids[start : start + 1000])
                rel = "rel_path" if old._has_rel else "NULL"
                marks = ",".join("?" * len(part.ids))
                extra = dict(
                    (r[0], r[1:])
                    for r in old._conn.execute(
                        f"SELECT id, {rel}, time, signature FROM scans WHERE id IN ({marks})",
                        [int(i) for i in part.ids],
                    )
                )
                got = [extra[int(i)] for i in part.ids]
                batch = ScanBatch(
                    paths=part.paths,
                    rel_paths=[g[0] for g in got],
                    signatures=np.stack([np.frombuffer(g[2], _SIG_DTYPE_V1) for g in got]),
                    features=part.features,
                    poses=part.poses,
                    times=np.array([np.nan if g[1] is None else g[1] for g in got]),
                    side_offsets=old.side_offsets,
                    side_signatures=(
                        np.stack([[views[int(i)][o] for o in old.side_offsets] for i in part.ids])
                        if old.side_offsets
                        else None
                    ),
                )
                with new:
                    _insert_rows(new, [int(i) for i in part.ids], batch, _encode_batch(batch))
            # Past what the format-1 map answered (its largest id): anything derived from
            # it is stale, since the signatures are now stored as float16.
            with new:
                gen = str((ids[-1] if ids else 0) + 1)
                new.execute("UPDATE meta SET value = ? WHERE key = 'generation'", (gen,))
        finally:
            new.close()
    except sqlite3.Error as exc:
        tmp.unlink(missing_ok=True)
        raise DatabaseError(path, f"cannot migrate ({exc})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        old.close()
    # The original keeps its inode under the backup name (a copy where the file system
    # has no hard links); `path` names a whole map at every moment.
    try:
        os.link(path, backup)
    except OSError:
        shutil.copy2(path, backup)
    os.replace(tmp, path)
    return before, path.stat().st_size, backup


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
        raise _sqlite_error(path, exc) from None
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


# SQLite's answers that mean "not allowed here" (permissions, a read-only volume), never
# damage: a map that cannot be written is opened read-only, not called corrupt.
_PERMISSION_ERRORS = ("SQLITE_READONLY", "SQLITE_CANTOPEN", "SQLITE_PERM", "SQLITE_AUTH")


def _is_permission_error(exc: sqlite3.Error) -> bool:
    return str(getattr(exc, "sqlite_errorname", "")).startswith(_PERMISSION_ERRORS)


def _note_on_stderr(line: str) -> None:
    print(f"note: {line}", file=sys.stderr, flush=True)


def _sqlite_error(path: Path, exc: sqlite3.Error, what: str = "corrupt database") -> DatabaseError:
    """One `DatabaseError` for an SQLite error: a permission problem said as such, any
    other as `what` (damage)."""
    if _is_permission_error(exc):
        return DatabaseError(
            path, f"cannot use the file ({exc}): check its and its folder's permissions"
        )
    return DatabaseError(path, f"{what} ({exc})")


def read_only_reason(path: str | Path) -> str | None:
    """Why this process cannot write the map at `path` (None when it can): the file, or
    its folder, where SQLite keeps the WAL's `-wal` and `-shm` files beside it."""
    path = Path(os.path.abspath(path))
    file_ok = os.access(path, os.W_OK)
    folder_ok = os.access(path.parent, os.W_OK | os.X_OK)
    if file_ok and folder_ok:
        return None
    if not file_ok and not folder_ok:
        return "neither the file nor its folder is writable here"
    return "the file is not writable here" if not file_ok else "its folder is not writable here"


def _sqlite_connect(path: Path, params: str) -> sqlite3.Connection:
    # The path as a URI: quoted, so that '?', '#' or '%' in a name stay part of it.
    uri = f"file:{quote(os.path.abspath(path), safe='/')}?{params}"
    conn = sqlite3.connect(uri, uri=True, timeout=30.0)
    try:
        # Damaged text reads as text (its checksum then fails) instead of raising.
        conn.text_factory = lambda b: b.decode("utf-8", "surrogateescape")
        conn.execute("PRAGMA busy_timeout=30000")
        # The first read opens the file and, under WAL, its -shm: fails here if it cannot.
        conn.execute("SELECT 1 FROM sqlite_master LIMIT 1").fetchall()
    except BaseException:
        conn.close()
        raise
    return conn


def _connect(path: Path, writable: bool) -> tuple[sqlite3.Connection, str | None]:
    """A connection to the map at `path`, and the note to give when it had to be opened
    read-only although the caller could have written (None otherwise).

    Where this process may write the file and its folder, the connection is read-write
    even for a reader (the last one to close folds the WAL in and removes -wal/-shm).
    Elsewhere (a read-only volume, a map of another user) it is `mode=ro`; when SQLite
    cannot even read that way (under WAL it needs a -shm file beside the map, which a
    read-only folder cannot take), `immutable=1`, which reads the file alone: right when
    nothing else writes it, and a pending WAL (writes not yet in the file) is refused."""
    reason = read_only_reason(path)
    if writable and reason is not None:
        raise DatabaseError(path, f"cannot write: {reason} (permission denied)")
    try:
        if reason is None:
            return _sqlite_connect(path, "mode=rw"), None
        try:
            return _sqlite_connect(path, "mode=ro"), f"opened read-only: {reason}"
        except sqlite3.OperationalError as exc:
            if not _is_permission_error(exc):
                raise
        wal = Path(f"{path}-wal")
        if wal.is_file() and wal.stat().st_size > 0:
            raise DatabaseError(
                path,
                f"cannot open read-only: {reason}, and its WAL ({wal.name}) holds writes that "
                f"SQLite reads only with a {path.name}-shm file it cannot create there; open "
                "it once where it can be written",
            )
        conn = _sqlite_connect(path, "mode=ro&immutable=1")
        return conn, f"opened read-only: {reason}"
    except sqlite3.Error as exc:
        raise _sqlite_error(path, exc, "corrupt or not an SQLite database") from None


def _read_meta(path: Path, conn: sqlite3.Connection) -> dict[str, str]:
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    except sqlite3.DatabaseError as exc:
        raise _sqlite_error(path, exc, "corrupt or not an SQLite database") from None
    if "meta" not in tables or "scans" not in tables:
        raise DatabaseError(path, "not a disco database (no meta/scans tables)")
    try:
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as exc:
        raise _sqlite_error(path, exc) from None
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


def _check_scans_table(path: Path, conn: sqlite3.Connection, version: int) -> None:
    try:
        cols = {r[1] for r in conn.execute("PRAGMA table_info(scans)")}
    except sqlite3.DatabaseError as exc:
        raise _sqlite_error(path, exc) from None
    missing = _SCAN_COLUMNS[min(max(version, 1), FORMAT_VERSION)] - cols
    if missing:
        lacks = ", ".join(sorted(missing))
        raise DatabaseError(path, f"not a disco database (scans lacks {lacks})")
