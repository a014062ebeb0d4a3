"""Migrating a format-1 map (before checksums: float32 signatures) to format 2, keeping
the original file beside it (`backup_path`): the conversion rounds float32 to float16.
Imported through `disco_cli.maps.database`; `Database.open(path, writable=True)` runs it."""

from __future__ import annotations

import os
import shutil
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError
from disco_cli.maps.database_codec import _SIG_DTYPE_V1, _encode_batch
from disco_cli.maps.database_file import _connect, _insert_rows, _new_file
from disco_cli.maps.database_types import ScanBatch


def backup_path(path: str | Path) -> Path:
    """Where migrating the format-1 map at `path` keeps the original: `map.db.v1`."""
    path = Path(path)
    return path.with_name(f"{path.name}.v1")


def _migrate(path: Path, open_reader: Callable[..., Any]) -> tuple[int, int, Path]:
    """Rewrite the format-1 map at `path` as format 2 (same ids, values and meta; rows
    checksummed as they are now) and rename it into place, keeping the original file as
    `backup_path(path)` (the conversion is lossy: float32 signatures become float16):
    (bytes before, after, the backup). A format-1 map with damaged rows is refused: it
    cannot be told what they were; so is one whose backup name is taken. `open_reader`
    opens it for reading (`Database._open`)."""
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
    old = open_reader(path, writable=False, verify=False)
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
