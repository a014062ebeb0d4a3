"""A map kept in Milvus: Milvus Lite (`milvus:PATH`) or a server (`milvus://HOST:PORT/NAME`).

`MilvusDatabase` is a `store.MapStore`, as the SQLite `database.Database` is (open,
create, append, rewrite, signatures, rows, poses, check, ...), so that every command
works on either; it shares no code with it that touches SQLite.
The optional extra is `pip install 'disco-cli[milvus]'` (pymilvus and milvus-lite).

Three collections, named `<NAME>_scans`, `<NAME>_views` and `<NAME>_meta` (NAME is
`disco` in Milvus Lite, the address's NAME on a server):

- scans: `id` (primary key, 1, 2, ... in insertion order), `sig` (the signature as a
  float vector: the float16-rounded values the SQLite map reads back, so both answer
  the same), `path`, `rel_path`, `time`, `x`, `y`, `z`, `yaw` (null when unknown),
  `features` (the SQLite map's deflated float16 blob, base64), `feature_scale`, and the
  row's checksums `crc` (id, path, pose, time, signature) and `feature_crc`.
- views (maps built with side views only): each scan's side-view signatures.
- meta: the SQLite map's meta keys (model, fingerprint, configurations, generation,
  next id), one row each.

Milvus has no multi-collection transactions: an append is three requests (side views,
scans, then the counters), made holding the map's writers' lock with its fence checked
before each (`milvus_lock.py`: without the lock two appends at once took the same ids,
and Milvus let the later rows replace the earlier ones). An append cut off between them
leaves its intent row: `check` reports it and `build-db --repair` finishes or undoes it
(`milvus_repair.py`). Milvus Lite takes one process per map folder; several writers
need a server (docs/scaling.md).
"""

from __future__ import annotations

import base64
import json
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DatabaseError, DiscoError
from disco_cli.maps.database_codec import _bad_signatures, _view_crc
from disco_cli.maps.database_file import FORMAT_VERSION, _note_on_stderr
from disco_cli.maps.database_paths import _locate
from disco_cli.maps.database_types import DamagedRows, MatchRows, ModelInfo, ScanBatch, damaged_line
from disco_cli.maps.index import AUTO_ANN_MIN_ROWS, check_index_kind
from disco_cli.maps.map_side_views import index_for
from disco_cli.maps.milvus_address import (
    MilvusAddress,
    connect,
    disconnect,
    parse_address,
    require_extra,
)
from disco_cli.maps.milvus_address import milvus_errors as _milvus_errors
from disco_cli.maps.milvus_index import MilvusIndex
from disco_cli.maps.milvus_lock import (
    LostLock,
    MapState,
    WriteLock,
    advance_counters,
    drop_intent,
    read_state,
    write_intent,
)
from disco_cli.maps.milvus_repair import check_map, settle, undo
from disco_cli.maps.milvus_schema import (
    create_collections,
    encode_rows,
    load_collections,
    read_meta,
    row_crc,
    vector_bytes,
)
from disco_cli.maps.store import StoreBase

__all__ = ["MilvusDatabase", "parse_address", "HNSW_MIN_ROWS"]

# Below this many scans the signatures are searched exactly (FLAT); from it on, by HNSW.
HNSW_MIN_ROWS = 200_000
_HNSW_BUILD = {"M": 16, "efConstruction": 128}
# Rows a single Milvus read returns (its query window is 16,384): 4,096 rows with their
# signatures or features (tens of MB), the whole window of ids and paths alone (Milvus
# Lite scans every row for each read: 4 s a read at a million scans).
_PAGE = 4096
_PAGE_NARROW = 16384
_WIDE_FIELDS = {"sig", "features"}


def _nan(v: Any) -> float:
    return np.nan if v is None else float(v)


class MilvusDatabase(StoreBase):
    """A map in Milvus: a `store.MapStore`, as `Database` is (the checks on models,
    batches and feature blobs are `StoreBase`'s, shared with it). Its writes hold the
    writers' lock and check its fence (`milvus_lock.py`); an append leaves an intent
    until its counters move. Use `open` or `create`."""

    def __init__(self, address: MilvusAddress, client: Any, meta: dict[str, str]):
        self.path = address
        self.address = address
        self._client = client
        self._take_meta(meta)
        # Never migrated, never opened read-only: a Milvus map has one format, and
        # Milvus, not the file system, says who may write.
        self.migrated = None
        self.migration_backup = None
        self.read_only = None
        self._scans = f"{address.name}_scans"
        self._views_c = f"{address.name}_views"
        self._meta_c = f"{address.name}_meta"
        self._writable = False
        self._on_note: Callable[[str], None] = _note_on_stderr

    # -- opening --------------------------------------------------------------

    @classmethod
    def open(
        cls,
        path: Any,
        writable: bool = False,
        verify: bool = False,
        on_note: Callable[[str], None] | None = None,
    ) -> MilvusDatabase:
        """The map at the `milvus:` address `path`; `writable` settles the appends of
        writers that died (`_open_for_writing`). `verify` is the SQLite map's: every
        Milvus row is verified as it is read."""
        address = parse_address(path)
        if address is None:
            raise DiscoError(f"{path}: not a milvus: address")
        require_extra(address)
        if address.lite and not Path(address.uri).exists():
            hint = "" if address.uri.endswith(".db") else " (a server is milvus://HOST:PORT/NAME)"
            raise DatabaseError(address, f"no such database{hint}")
        client = connect(address)
        try:
            load_collections(address, client)
            meta = read_meta(address, client)
            db = cls(address, client, meta)
            if on_note is not None:
                db._on_note = on_note
            if writable:
                db._writable = True
                db._open_for_writing()
            return db
        except BaseException:
            disconnect(address, client)
            raise

    @classmethod
    def create(
        cls,
        path: Any,
        model: ModelInfo,
        first: ScanBatch,
        disco_version: str = "",
        extra_meta: dict[str, str] | None = None,
        overwrite: bool = False,
    ) -> MilvusDatabase:
        """A new map at `path` holding `first`. An existing one is refused unless
        `overwrite` (its collections are dropped)."""
        address = parse_address(path)
        if address is None:
            raise DiscoError(f"{path}: not a milvus: address")
        if not first.paths:
            raise ValueError("the first batch of a new database must not be empty")
        if not disco_version:
            # deferred: importlib.metadata, read for a new map only
            from disco_cli import __version__ as disco_version
        dim = int(first.signatures.shape[1])
        meta = {
            "disco_version": disco_version,
            "model_name": model.name,
            "fingerprint": model.fingerprint,
            "model_config": json.dumps(model.model_config, sort_keys=True),
            "bev_config": json.dumps(model.bev_config, sort_keys=True),
            "signature_dim": str(dim),
            "feature_shape": json.dumps(list(first.features.shape[1:])),
            **(extra_meta or {}),
            "format_version": str(FORMAT_VERSION),
            "generation": "0",
            "next_id": "1",
            "signature_dtype": "float16",
            "feature_dtype": "float16",
            "feature_codec": "deflate+base64",
            "store": "milvus",
        }
        if first.side_offsets:
            meta["side_views_m"] = json.dumps(list(first.side_offsets))
        client = connect(address)
        try:
            create_collections(address, client, dim, bool(first.side_offsets), overwrite)
            db = cls(address, client, meta)
            db._writable = True
            # The meta goes in last: a map without it is no map (and is replaced).
            db.append(first, _meta_first=meta)
            return db
        except BaseException:
            disconnect(address, client)
            raise

    def close(self) -> None:
        if self._client is not None:
            client, self._client = self._client, None
            disconnect(self.address, client)

    # -- writing ----------------------------------------------------------------

    @_milvus_errors
    def append(self, batch: ScanBatch, _meta_first: dict | None = None) -> list[int]:
        """Append one batch; their ids. Three requests (side views, scans, counters)
        under the writers' lock, its fence checked before each (`milvus_lock.py`)."""
        if not batch.paths:
            return []
        self.check_batch_shapes(batch)
        if _meta_first is not None:  # a new map: no other writer knows it yet
            ids = list(range(1, 1 + len(batch.paths)))
            self._put_rows(*self._encode(ids, batch), lock=None)
            # The meta goes in last: a map without it is no map (and is replaced).
            self._write_meta(self.meta)
            advance_counters(self._client, self._meta_c, MapState(), len(ids) + 1, 1)
            self.meta.update(next_id=str(len(ids) + 1), generation="1")
            self._choose_index()
            return ids
        with WriteLock(self._client, self._meta_c, self.path) as lock:
            state = lock.check()
            # Another process may have appended since this one last did.
            start = self._count_in_orphans(state)
            ids = list(range(start, start + len(batch.paths)))
            rows, views = self._encode(ids, batch)
            intent = {"start": start, "end": ids[-1] + 1, "token": lock.token}
            intent["crcs"] = [r["crc"] for r in rows]
            write_intent(self._client, self._meta_c, lock.epoch, intent)
            try:
                lock.check()  # after the intent: see milvus_lock.py
                self._put_rows(rows, views, lock)
                state = lock.check()
            except LostLock:
                undo(self, lock.epoch, intent)
                raise
            advance_counters(self._client, self._meta_c, state, intent["end"], state.generation + 1)
            drop_intent(self._client, self._meta_c, lock.epoch, None)
            self.meta.update(next_id=str(intent["end"]), generation=str(state.generation + 1))
            self._choose_index()
        return ids

    @_milvus_errors
    def rewrite(self, ids: Sequence[int], batch: ScanBatch) -> None:
        """Replace the rows of the scans `ids` (`disco build-db --repair`)."""
        ids = [int(i) for i in ids]
        if len(ids) != len(batch.paths):
            raise ValueError(f"{len(ids)} ids for {len(batch.paths)} scans")
        if not ids:
            return
        self.check_batch_shapes(batch)
        rows, views = self._encode(ids, batch)
        with WriteLock(self._client, self._meta_c, self.path) as lock:
            lock.check()
            if self.side_offsets:
                self._client.delete(self._views_c, filter=f"scan_id in {ids}")
            self._put_rows(rows, views, lock, upsert=True)
            state = lock.check()
            advance_counters(self._client, self._meta_c, state, state.next_id, state.generation + 1)
            self.meta.update(next_id=str(state.next_id), generation=str(state.generation + 1))
        for i in ids:
            self.damaged.pop(i, None)

    def _encode(self, ids: list[int], batch: ScanBatch) -> tuple[list[dict], list[dict]]:
        # Relative paths mean nothing on a server: none are stored there.
        rels = batch.rel_paths if self.address.lite else [None] * len(ids)
        return encode_rows(self.path, ids, batch, rels)  # type: ignore[arg-type]

    def _put_rows(
        self, rows: list[dict], views: list[dict], lock: WriteLock | None, upsert: bool = False
    ) -> None:
        # Views first: a scan row is only ever seen with its views stored. The views'
        # keys are the scan's id and the view's number: a rewrite deletes them first.
        if views:
            (self._client.upsert if upsert else self._client.insert)(self._views_c, views)
            if lock is not None:
                lock.check()
        (self._client.upsert if upsert else self._client.insert)(self._scans, rows)

    def _write_meta(self, values: dict[str, str]) -> None:
        """Meta keys (the model's record, `index_type`); never the counters."""
        self._client.upsert(
            self._meta_c, [{"key": k, "value": v, "v": [0.0, 0.0]} for k, v in values.items()]
        )

    def _read_counters(self) -> MapState:
        state = read_state(self._client, self._meta_c)
        self.meta.update(next_id=str(state.next_id), generation=str(state.generation))
        return state

    @_milvus_errors
    def _open_for_writing(self) -> None:
        lock = WriteLock(self._client, self._meta_c, self.path)
        if self.address.lite:
            # One process per Milvus Lite folder: another process's claim is a dead
            # writer's; this process's own may be a live one's (another open map).
            lock.clear_other_processes()
        with lock:
            self._count_in_orphans(lock.check())

    def _count_in_orphans(self, state: MapState) -> int:
        """Rows past every id given or being given, without an intent (an older disco's
        interrupted append): counted in. The first id free now."""
        self.meta.update(next_id=str(state.next_id), generation=str(state.generation))
        start = state.free_from()
        got = self._query(f"id >= {start}", ["id"])
        if not got:
            return start
        end = max(int(r["id"]) for r in got) + 1
        advance_counters(self._client, self._meta_c, state, end, state.generation + 1)
        self.meta.update(next_id=str(end), generation=str(state.generation + 1))
        return end

    @_milvus_errors
    def settle(self) -> list[str]:
        """Finish or undo every append cut off halfway (`milvus_repair.settle`)."""
        return settle(self)

    def _choose_index(self) -> None:
        """FLAT (exact) below `HNSW_MIN_ROWS` scans, HNSW from there on."""
        # next_id - 1 bounds the rows (ids are never reused): no count per append below
        # the threshold (a count reads every row in Milvus Lite: 0.4 s at 40,000).
        if self.meta.get("index_type") == "HNSW" or int(self.meta["next_id"]) - 1 < HNSW_MIN_ROWS:
            return
        if len(self) < HNSW_MIN_ROWS:
            return
        c = self._client
        if self._index_type() != "HNSW":  # an interrupted switch may have made it already
            c.release_collection(self._scans)
            c.drop_index(self._scans, "sig")
            params = c.prepare_index_params()
            params.add_index(
                field_name="sig", index_type="HNSW", metric_type="L2", params=_HNSW_BUILD
            )
            try:
                c.create_index(self._scans, params)
            except Exception:
                # pymilvus resends a call the server cut off (Milvus Lite's gRPC server
                # does so when a call waits minutes behind its compaction): the resent
                # one finds the index the first one made.
                if self._index_type() != "HNSW":
                    raise
        c.load_collection(self._scans)
        self.meta["index_type"] = "HNSW"
        self._write_meta({"index_type": "HNSW"})

    def _index_type(self) -> str | None:
        try:
            return self._client.describe_index(self._scans, "sig").get("index_type")
        except Exception:  # no index on the field
            return None

    # -- reading ----------------------------------------------------------------

    def _query(self, filt: str, fields: list[str], collection: str | None = None) -> list[dict]:
        """Every row matching `filt` (paged by id: Milvus returns at most 16,384 a call)."""
        key = "scan_id" if collection == self._views_c else "id"
        out: list[dict] = []
        last = -(2**62)
        size = _PAGE if _WIDE_FIELDS & set(fields) else _PAGE_NARROW
        while True:
            page = self._client.query(
                collection or self._scans,
                filter=f"({filt}) and {key} > {last}" if filt else f"{key} > {last}",
                output_fields=fields,
                limit=size,
                consistency_level="Strong",
            )
            page = [dict(r) for r in page]
            out += page
            if len(page) < size:
                return out
            # Views share scan ids: page by the largest scan whose views all came.
            last = max(int(r[key]) for r in page) - (1 if key == "scan_id" else 0)
            if key == "scan_id":
                out = [r for r in out if int(r[key]) <= last]

    @property
    @_milvus_errors
    def generation(self) -> int:
        try:
            return read_state(self._client, self._meta_c).generation
        except ValueError:
            raise DatabaseError(self.path, "corrupt map: bad generation") from None

    @_milvus_errors
    def __len__(self) -> int:
        got = self._client.query(
            self._scans, filter="", output_fields=["count(*)"], consistency_level="Strong"
        )
        return int(got[0]["count(*)"])

    def next_id(self) -> int:
        return int(self.meta["next_id"])

    @_milvus_errors
    def ids(self) -> np.ndarray:
        return np.sort(np.array([int(r["id"]) for r in self._query("", ["id"])], dtype=np.int64))

    def _names(self) -> list[dict]:
        rows = self._query("", ["id", "path", "rel_path"])
        return sorted(rows, key=lambda r: int(r["id"]))

    @_milvus_errors
    def paths(self) -> list[str]:
        return [r["path"] for r in self._names()]

    @_milvus_errors
    def locate(self, stored: str, scan_root: str | Path | None = None) -> Path | None:
        got = self._client.query(
            self._scans,
            filter=f"path == {json.dumps(stored)}",
            output_fields=["rel_path"],
            consistency_level="Strong",
        )
        rel = got[0]["rel_path"] if got else None
        return _locate(stored, rel, Path(os.fspath(self.address)), scan_root)

    @_milvus_errors
    def locations(self, scan_root: str | Path | None = None) -> list[str]:
        out = []
        where = Path(os.fspath(self.address))
        for r in self._names():
            found = _locate(r["path"], r["rel_path"], where, scan_root)
            out.append(str(found) if found is not None else os.path.abspath(r["path"]))
        return out

    @_milvus_errors
    def stored_names(self, ids: Iterable[int]) -> dict[int, tuple[str, str | None]]:
        ids = [int(i) for i in ids]
        if not ids:
            return {}
        rows = self._query(f"id in {ids}", ["id", "path", "rel_path"])
        return {int(r["id"]): (r["path"], r["rel_path"]) for r in rows}

    @_milvus_errors
    def has_poses(self) -> bool:
        got = self._client.query(
            self._scans,
            filter="x is not null",
            output_fields=["id"],
            limit=1,
            consistency_level="Strong",
        )
        return bool(got)

    @_milvus_errors
    def existing(self, paths: Iterable[str]) -> set[str]:
        stored = set(self.paths())
        return {p for p in paths if p in stored}

    def size_bytes(self) -> int:
        if not self.address.lite:
            return 0  # a server's storage is its own
        total = 0
        for root, _, files in os.walk(self.address.uri):
            for f in files:
                try:
                    total += os.path.getsize(os.path.join(root, f))
                except OSError:
                    pass
        return total

    _SCAN_FIELDS = ["id", "sig", "path", "rel_path", "time", "x", "y", "z", "yaw", "crc"]

    def _scan_problem_m(self, row: dict) -> str | None:
        """What is wrong with a scan row (`Database._scan_problem`'s checks), or None."""
        sig = row.get("sig")
        if sig is None or len(sig) != self.signature_dim:
            return f"signature is not {self.signature_dim} values"
        if not isinstance(row.get("path"), str):
            return "path is not text"
        if row.get("crc") != row_crc(int(row["id"]), row):
            return "checksum mismatch (signature, pose, time or path changed)"
        return None

    def _sound_rows(self, rows: list[dict]) -> tuple[list[dict], np.ndarray, dict[int, str]]:
        sound, bad = [], {}
        for r in rows:
            problem = self._scan_problem_m(r)
            if problem:
                bad[int(r["id"])] = problem
            else:
                sound.append(r)
        sigs = np.array([r["sig"] for r in sound], dtype=np.float32).reshape(
            len(sound), self.signature_dim
        )
        out = _bad_signatures(sigs)
        for k in np.flatnonzero(out):
            bad[int(sound[k]["id"])] = "signature is not finite or out of range"
        keep = [r for r, o in zip(sound, out) if not o]
        return keep, sigs[~out], bad

    @_milvus_errors
    def signatures(self) -> tuple[np.ndarray, np.ndarray]:
        rows = sorted(self._query("", self._SCAN_FIELDS), key=lambda r: int(r["id"]))
        if not rows:
            raise DatabaseError(self.path, "the database is empty")
        sound, sigs, bad = self._sound_rows(rows)
        self._note_damaged(bad, {int(r["id"]): r.get("path") for r in rows})
        if not sound:
            raise DatabaseError(
                self.path, "no sound scan: " + damaged_line(self.damaged, self.path)
            )
        return np.array([int(r["id"]) for r in sound], dtype=np.int64), sigs

    def _view_rows(self) -> list[dict]:
        rows = self._query("", ["scan_id", "offset_m", "sig", "crc"], self._views_c)
        return sorted(rows, key=lambda r: (int(r["scan_id"]), float(r["offset_m"])))

    def _view_problems(self, rows: list[dict]) -> tuple[list[dict], dict[int, str]]:
        sound, bad = [], {}
        for r in rows:
            rid = int(r["scan_id"])
            sig = r.get("sig")
            if sig is None or len(sig) != self.signature_dim:
                bad[rid] = "a side view has another size"
            elif r.get("crc") != _view_crc(rid, float(r["offset_m"]), vector_bytes(sig), 1.0):
                bad[rid] = "a side view fails its checksum"
            else:
                sound.append(r)
        return sound, bad

    @_milvus_errors
    def side_signatures(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.side_offsets:
            return np.empty(0, np.int64), np.empty((0, self.signature_dim), np.float32)
        sound, bad = self._view_problems(self._view_rows())
        self._note_damaged(bad, {i: "a side view" for i in bad})
        ids = np.array([int(r["scan_id"]) for r in sound], dtype=np.int64)
        sigs = np.array([r["sig"] for r in sound], np.float32).reshape(-1, self.signature_dim)
        return ids, sigs

    @_milvus_errors
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        rows = sorted(self._query("", self._SCAN_FIELDS), key=lambda r: int(r["id"]))
        _, _, bad = self._sound_rows(rows)
        self._note_damaged(bad, {int(r["id"]): r.get("path") for r in rows})
        arr = np.array(
            [
                (np.nan,) * 5
                if int(r["id"]) in bad
                else tuple(_nan(r[k]) for k in ("time", "x", "y", "z", "yaw"))
                for r in rows
            ],
            dtype=np.float64,
        ).reshape(-1, 5)
        return arr[:, 1:5], arr[:, 0]

    @_milvus_errors
    def rows(self, ids: Sequence[int] | np.ndarray) -> MatchRows:
        """Paths, poses and features of the scans `ids`, in that order; damaged or
        missing rows raise `DamagedRows` (recorded in `damaged`), as `Database.rows`."""
        ids = [int(i) for i in np.asarray(ids).reshape(-1)]
        want = list(dict.fromkeys(ids))
        found: dict[int, dict] = {}
        fields = [*self._SCAN_FIELDS, "features", "feature_scale", "feature_crc"]
        for s in range(0, len(want), 500):
            for r in self._query(f"id in {want[s : s + 500]}", fields):
                found[int(r["id"])] = r
        bad: dict[int, str] = {}
        decoded: dict[int, np.ndarray] = {}
        for rid in want:
            r = found.get(rid)
            if r is None:
                bad[rid] = "row is missing"
                continue
            problem = self._scan_problem_m(r)
            if problem is None:
                feats, problem = self._features_of(rid, r)
                if feats is not None:
                    decoded[rid] = feats
            if problem is not None:
                bad[rid] = problem
        if bad:
            self._note_damaged(bad, {i: (found[i]["path"] if i in found else "?") for i in bad})
            raise DamagedRows(self.path, {i: self.damaged[i] for i in bad})
        feats = (
            np.stack([decoded[i] for i in ids])
            if ids
            else np.empty((0, *self.feature_shape), np.float32)
        )
        poses = np.array(
            [[_nan(found[i][k]) for k in ("x", "y", "z", "yaw")] for i in ids], np.float64
        ).reshape(-1, 4)
        return MatchRows(np.asarray(ids, np.int64), [found[i]["path"] for i in ids], poses, feats)

    def _features_of(self, rid: int, r: dict) -> tuple[np.ndarray | None, str | None]:
        text = r.get("features")
        try:
            data = base64.b64decode(text, validate=True) if isinstance(text, str) else None
        except (ValueError, TypeError):
            return None, "features are not base64"
        scale = r.get("feature_scale")
        return self._decoded_features(
            rid, None if scale is None else float(scale), data, r.get("feature_crc")
        )

    @_milvus_errors
    def check(self) -> list[str]:
        """Every problem of the map (`milvus_repair.check_map`). On a map opened for
        writing (`build-db --repair`) the appends cut off halfway are settled first."""
        if self._writable:
            for line in self.settle():
                self._on_note(f"{self.address}: {line}")
        return check_map(self)

    # -- searching --------------------------------------------------------------

    def index_for(self, kind: str = "auto", note: Any = None) -> tuple[np.ndarray, Any]:
        """`(ids, index)` for `Map`. `ann`, and `auto` from `AUTO_ANN_MIN_ROWS` scans:
        searched in Milvus (`MilvusIndex`; FLAT, HNSW from `HNSW_MIN_ROWS`). `exact`,
        `auto` below that, and maps with side views: the signatures are read once and
        searched here as the SQLite map's are (`side_views.index_for`): Milvus Lite's
        own search is pure Python, ~0.2 s a query at 20,000 scans (docs/scaling.md)."""
        check_index_kind(kind)
        small = kind == "auto" and len(self) < AUTO_ANN_MIN_ROWS
        if kind == "exact" or small or self.side_offsets:
            return index_for(self)

        ids = self.ids()
        if not len(ids):
            raise DatabaseError(self.path, "the database is empty")
        return ids, MilvusIndex(self, ids)
