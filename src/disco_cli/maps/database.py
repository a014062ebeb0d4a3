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
  to its side (`map_side_views.py`), searched beside the scans'.

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
process may not write (its file or folder) opens read-only (`immutable=1` for a file
nobody may write or where SQLite cannot put the WAL's -shm file beside it, else
`mode=ro`), with one note, leaving no -wal or -shm that would stop a later writer; a
writer makes its own unwritable -wal and -shm writable, or names them for removal.
"""

from __future__ import annotations

import json
import os
import sqlite3
import stat
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError

# The codec: what this module uses, and what others (tests) import from here.
from disco_cli.maps.database_codec import (  # noqa: F401
    _FEAT_DTYPE,
    _SCAN_ROW,
    _SIG_DTYPE,
    _SIG_DTYPE_V1,
    _bad_signatures,
    _encode_batch,
    _encode_features,
    _feature_crc,
    _scaled,
    _scan_crc,
    _view_crc,
)
from disco_cli.maps.database_file import (
    FORMAT_VERSION,
    _check_header,
    _check_integrity,
    _check_scans_table,
    _connect,
    _insert_rows,
    _new_file,
    _note_on_stderr,
    _read_meta,
    _sql_errors,
    _sqlite_error,
    read_only_reason,
)
from disco_cli.maps.database_migration import _migrate, backup_path
from disco_cli.maps.database_paths import _locate, stored_paths
from disco_cli.maps.database_rows import RowReader
from disco_cli.maps.database_types import DamagedRows, MatchRows, ModelInfo, ScanBatch, damaged_line
from disco_cli.maps.index import index_for_database

__all__ = [
    "FORMAT_VERSION",
    "Database",
    "DamagedRows",
    "ModelInfo",
    "ScanBatch",
    "MatchRows",
    "backup_path",
    "damaged_line",
    "read_only_reason",
    "stored_paths",
]


class Database(RowReader):
    """An open map database, one SQLite file: a `store.MapStore` whose every write is one
    SQLite transaction (`_write_transaction`). Use `Database.open(path)` or
    `Database.create(path, ...)` (`store.open_store` picks the store an address names).

    `damaged` maps the id of every scan whose row (or one of its rows: features, a side
    view) was found damaged by a read so far to what names it (its stored path); `check()`
    fills it for the whole file."""

    def __init__(self, path: Path, conn: sqlite3.Connection, meta: dict[str, str]):
        self.path = path
        self._conn = conn
        self._take_meta(meta)
        # rows(): the last rows read, decoded (id -> path, pose, features), valid while
        # the file's generation is the one they were read at.
        self._cache: OrderedDict[int, tuple] = OrderedDict()
        self._cache_generation: int | None = None
        # Stored size of one signature (of features: `StoreBase._take_meta`).
        sig_dtype = _SIG_DTYPE if self.format_version >= 2 else _SIG_DTYPE_V1
        self._nsig = self.signature_dim * sig_dtype.itemsize
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
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
        except sqlite3.DatabaseError as exc:
            raise _sqlite_error(path, exc, "corrupt or unreadable database") from None
        if self.side_offsets and "side_views" not in tables:
            raise DatabaseError(path, "corrupt database: side views named but not stored")
        if self.checksummed and "features" not in tables:
            raise DatabaseError(path, "corrupt database: no features table")

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
        integrity_check` (every page: about 0.7 ms per MB of file from the page cache,
        docs/benchmarks.md) runs only with `verify=True`, for writing (a write onto a
        damaged b-tree can spread the damage), and in `check()` (`disco info --check`).
        A refused file is not modified.

        A map this process may not write (its file or folder; a read-only volume) opens
        read-only, and `on_note` hears one line saying so (default: `note: ...` on
        stderr); `read_only` holds it. Opening a format-1 file for writing migrates it to
        format 2 and keeps the original beside it (`migrated`, `migrated_line()`).
        """
        path = Path(path)
        db = cls._open(path, writable, verify)
        if writable and db.format_version < FORMAT_VERSION:
            db.close()
            before, after, backup = _migrate(path, cls._open)
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
        overwrite: bool = False,
    ) -> Database:
        """Create a new database holding `first` (which must not be empty); an existing
        file is refused unless `overwrite` (it and its -wal and -shm are removed first).

        The file appears at `path` only once its first batch is committed: it is built
        under a temporary name and renamed into place.
        """
        path = Path(path)
        if overwrite:
            for suffix in ("", "-wal", "-shm"):
                Path(str(path) + suffix).unlink(missing_ok=True)
        if path.exists():
            raise DatabaseError(path, "already exists")
        if not first.paths:
            raise ValueError("the first batch of a new database must not be empty")
        if not disco_version:
            # deferred: __version__ reads importlib.metadata (50-150 ms); queries never need it
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

    def close(self) -> None:
        self._conn.close()

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

    @_sql_errors
    def existing(self, paths: Iterable[str]) -> set[str]:
        """Which of `paths` are stored already (for resuming a build)."""
        stored = set(r[0] for r in self._conn.execute("SELECT path FROM scans"))
        return {p for p in paths if p in stored}

    def size_bytes(self) -> int:
        """The file's size with its -wal and -shm."""
        total = 0
        for suffix in ("", "-wal", "-shm"):
            p = Path(str(self.path) + suffix)
            if p.exists():
                total += p.stat().st_size
        return total

    def index_for(self, kind: str = "auto", note: Any = None) -> tuple[np.ndarray, Any]:
        """`(ids, index)` to search this map with (`maps.index.index_for_database`)."""
        return index_for_database(self, kind, note)
