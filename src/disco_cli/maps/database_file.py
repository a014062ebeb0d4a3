"""The map database's SQLite file: its schema, creating one, and opening one: the header
and size checks, read-only opening where this process may not write, the integrity
check, the meta table; and SQLite's errors turned into one `DatabaseError` line that
never calls a permission problem damage. Imported through `disco_cli.maps.database`."""

from __future__ import annotations

import functools
import json
import os
import sqlite3
import stat
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote

from disco_cli.errors import DatabaseError
from disco_cli.maps.database_codec import (
    _SCAN_ROW,
    _feature_crc,
    _none_if_nan,
    _scan_crc,
    _view_crc,
)
from disco_cli.maps.database_types import ScanBatch

FORMAT_VERSION = 2
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER_SIZE = 100
# At most this many problems of the integrity check are named in the error line.
_PROBLEMS_SHOWN = 3
# Large pages keep a row's blobs in its b-tree leaf: no half-empty overflow page per
# row (about 2 KiB of a 4 KiB page's worth); ~7 feature rows and ~30 scan rows a page.
_PAGE_SIZE = 65536

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


_F = TypeVar("_F", bound=Callable[..., Any])


def _sql_errors(func: _F) -> _F:
    """Turn an SQLite error met while reading or writing into one `DatabaseError`
    naming the file: a page that turns out damaged only when it is read, a disk error."""

    @functools.wraps(func)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return func(self, *args, **kwargs)
        except sqlite3.DatabaseError as exc:
            raise _sqlite_error(self.path, exc, "corrupt or unreadable database") from None

    return wrapper  # type: ignore[return-value]


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


def _side_files_writable(path: Path) -> None:
    """Make the map's `-wal` and `-shm` writable where this process may write the map
    itself, or say in one line which to remove.

    SQLite creates them with the map's own permissions, so a read-only open of a 0444
    map (by an older disco, the sqlite3 shell, another user) leaves them 0444, and once
    the map is made writable every write fails with "attempt to write a readonly
    database". Ours are given the map's permissions (chmod disturbs no process that has
    them open); another user's cannot be, and are named."""
    mode = None
    for side in (Path(f"{path}-wal"), Path(f"{path}-shm")):
        try:
            st = side.stat()
        except FileNotFoundError:
            continue
        except OSError:
            st = None
        if os.access(side, os.R_OK | os.W_OK):
            continue
        if st is not None and st.st_uid == os.geteuid():
            mode = stat.S_IMODE(path.stat().st_mode) if mode is None else mode
            try:
                os.chmod(side, mode | stat.S_IRUSR | stat.S_IWUSR)
                continue
            except OSError:
                pass
        raise DatabaseError(
            path,
            f"cannot write: {side.name} beside it is not writable here (left by a read-only "
            f"open?); remove {path.name}-wal and {path.name}-shm while no process has the "
            "map open, or make them writable",
        )


def _connect(path: Path, writable: bool) -> tuple[sqlite3.Connection, str | None]:
    """A connection to the map at `path`, and the note to give when it had to be opened
    read-only although the caller could have written (None otherwise).

    Where this process may write the file and its folder, the connection is read-write
    even for a reader (the last one to close folds the WAL in and removes -wal/-shm),
    once its -wal and -shm are writable too (`_side_files_writable`). Elsewhere (a
    read-only volume, a map of another user) it is read-only, and leaves nothing beside
    the map that could stop a later writer:

    - a map that nobody may write (no write permission bit: a 0444 file) is opened
      `immutable=1`, which reads the file alone and creates no -wal or -shm, unless
      its WAL holds writes not yet in the file;
    - otherwise `mode=ro` (its owner may be writing it meanwhile: SQLite then needs the
      -shm beside it to see those writes), and where SQLite cannot even read that way
      (a read-only folder cannot take the -shm), `immutable=1`; a pending WAL is refused
      then. A writer that later finds those -wal and -shm files of another user
      unwritable says which to remove."""
    reason = read_only_reason(path)
    if writable and reason is not None:
        raise DatabaseError(path, f"cannot write: {reason} (permission denied)")
    try:
        if reason is None:
            _side_files_writable(path)
            return _sqlite_connect(path, "mode=rw"), None
        wal = Path(f"{path}-wal")
        pending = wal.is_file() and wal.stat().st_size > 0
        if not pending and not stat.S_IMODE(path.stat().st_mode) & 0o222:
            return _sqlite_connect(path, "mode=ro&immutable=1"), f"opened read-only: {reason}"
        try:
            return _sqlite_connect(path, "mode=ro"), f"opened read-only: {reason}"
        except sqlite3.OperationalError as exc:
            if not _is_permission_error(exc):
                raise
        if pending:
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
