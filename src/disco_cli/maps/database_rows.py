"""Reading a map's rows and verifying each as it is read: `RowReader`, the part of
`Database` that loads signatures, poses and the rows a query re-ranks, checks every row
(checksum, sizes, values) and records damaged ones, and `check()`, the whole file's
check (`disco info --check`). Imported through `disco_cli.maps.database`."""

from __future__ import annotations

import sqlite3
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from disco_cli.errors import DatabaseError
from disco_cli.maps.database_codec import (
    _FEAT_DTYPE,
    _SCAN_ROW,
    _SIG_DTYPE,
    _SIG_DTYPE_V1,
    _bad_signatures,
    _scan_crc,
    _view_crc,
)
from disco_cli.maps.database_file import _sql_errors
from disco_cli.maps.database_types import DamagedRows, MatchRows, damaged_line
from disco_cli.maps.store import _NOT_FINITE, StoreBase

# Decoded feature rows `Database.rows` keeps (about 38 KB each for the default model).
_CACHED_ROWS = 256


class RowReader(StoreBase):
    """What `Database` reads and verifies (on `StoreBase`'s checks). Its attributes are
    `Database`'s (set there)."""

    path: Path
    _conn: sqlite3.Connection
    damaged: dict[int, str]
    signature_dim: int
    feature_shape: tuple[int, ...]
    side_offsets: tuple[float, ...]
    _has_rel: bool
    _nsig: int
    _nfeat: int
    _cache: OrderedDict[int, tuple]
    _cache_generation: int | None

    generation: int

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
        poses = np.array([e[1] for e in entries], dtype=np.float64).reshape(-1, 4)
        found = np.asarray(ids, dtype=np.int64), [e[0] for e in entries], poses
        if not entries:
            return MatchRows(*found, np.empty((0, *self.feature_shape), dtype=np.float32))
        # The cached arrays themselves (never written to): stacked only if asked for.
        return MatchRows(*found, feature_rows=[e[2] for e in entries])

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
        decoded.flags.writeable = False  # `rows` hands the cached arrays out as they are
        for k, rid in enumerate(order):
            row = found[rid]
            pose = tuple(np.nan if v is None else float(v) for v in row[4:8])
            self._cache[rid] = (row[1], pose, decoded[k])

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
