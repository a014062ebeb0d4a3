"""What a map store is: `MapStore`, everything `Map`, the commands, the service and the
copy ask of a map's storage, with each member's contract; `StoreBase`, the part both
stores share that touches no storage (the model, batch and feature-blob checks); and
`store_class`/`open_store`, which pick the store an address names.

Two stores implement it, each owning its writes (docs/database.md, "What a store is"):

- `database.Database`, one SQLite file: every write is one SQLite transaction
  (`Database._write_transaction`), all or nothing; readers see a consistent state (WAL).
- `milvus_store.MilvusDatabase`, Milvus Lite or a server: Milvus has no transactions
  across collections, so a write is several requests made holding the map's writers'
  lock with its fence checked before each (`milvus_lock.py`), and an append leaves an
  intent row until its counters move: one cut off halfway is reported by `check` and
  finished or undone by `build-db --repair` (`milvus_repair.py`).
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from disco_cli.errors import DatabaseError
from disco_cli.maps.database_codec import _FEAT_DTYPE, _feature_crc
from disco_cli.maps.database_types import MatchRows, ModelInfo, ScanBatch
from disco_cli.maps.map_side_views import side_views_m
from disco_cli.maps.milvus_address import parse_address

__all__ = ["MapStore", "StoreBase", "open_store", "store_class"]

_NOT_FINITE = "features are not finite"


@runtime_checkable
class MapStore(Protocol):
    """An open map: its record, its rows (read and verified), its writes. A damaged row
    is never used silently: reads leave it out and record it in `damaged`, or raise
    `DamagedRows`; every other failure is one `DatabaseError` naming the map."""

    path: Any
    """Where the map is (a file's `Path`, or a `MilvusAddress`): what errors name."""
    meta: dict[str, str]
    """The map's stored record (model, configurations, versions, `model_source`)."""
    model: ModelInfo
    """The model that built the map; `check_model` refuses another."""
    format_version: int
    """The stored format's version (1: unverified rows; 2: checksummed)."""
    signature_dim: int
    """The length of one stored signature."""
    feature_shape: tuple[int, ...]
    """The shape of one scan's stored features."""
    side_offsets: tuple[float, ...]
    """The side views' offsets in metres (none: a map without side views)."""
    damaged: dict[int, str]
    """`{id: what names it}` of every damaged scan a read so far (or `check`) met."""
    migrated: tuple[int, int] | None
    """`(bytes before, bytes after)` when opening for writing migrated the map, else None."""
    migration_backup: Path | None
    """Where the migrated map's original was kept, else None."""
    read_only: str | None
    """Why the map was opened read-only although writing was not refused, else None."""

    @classmethod
    def open(
        cls,
        path: Any,
        writable: bool = False,
        verify: bool = False,
        on_note: Callable[[str], None] | None = None,
    ) -> MapStore:
        """The existing map at `path`, or one `DatabaseError`; a refused map is not modified."""
        ...

    @classmethod
    def create(
        cls,
        path: Any,
        model: ModelInfo,
        first: ScanBatch,
        disco_version: str = "",
        extra_meta: dict[str, str] | None = None,
        overwrite: bool = False,
    ) -> MapStore:
        """A new map holding `first` (not empty), open for writing; an existing one is
        refused unless `overwrite`. No map is left at `path` if this fails."""
        ...

    def close(self) -> None:
        """Let go of the map (its connection); closing twice is harmless."""
        ...

    def __enter__(self) -> MapStore:
        """The store itself; leaving the block closes it."""
        ...

    def __exit__(self, *exc: object) -> None:
        """`close()`."""
        ...

    def migrated_line(self) -> str:
        """One line saying what opening migrated ('' if nothing)."""
        ...

    def check_model(self, model: ModelInfo) -> None:
        """Nothing, or one `DatabaseError` when `model` is not the one that built the map."""
        ...

    @property
    def checksummed(self) -> bool:
        """Whether rows carry checksums (format 2)."""
        ...

    @property
    def generation(self) -> int:
        """A number every write (any process's) raises: a key for what is derived from the map."""
        ...

    def append(self, batch: ScanBatch) -> list[int]:
        """Store `batch` as new scans, ids after every id given; their ids. A failed append
        stores none of it (SQLite: one transaction; Milvus: undone, or left as an intent
        that `check` reports and `settle` finishes or undoes)."""
        ...

    def rewrite(self, ids: Sequence[int], batch: ScanBatch) -> None:
        """Replace the rows of the scans `ids` with `batch` (`build-db --repair`); they are
        no longer `damaged`."""
        ...

    def __len__(self) -> int:
        """How many scans are stored now."""
        ...

    def next_id(self) -> int:
        """The id the next appended scan gets (ids are never reused)."""
        ...

    def ids(self) -> np.ndarray:
        """Every stored id, ascending (the rows of `paths`, `poses`, `locations`)."""
        ...

    def paths(self) -> list[str]:
        """Every stored path, in id order."""
        ...

    def locate(self, stored: str, scan_root: str | Path | None = None) -> Path | None:
        """Where the stored scan `stored` is now (`database_paths._locate`), or None."""
        ...

    def locations(self, scan_root: str | Path | None = None) -> list[str]:
        """Every stored scan's location now (`locate`; else its stored path), absolute."""
        ...

    def stored_names(self, ids: Iterable[int]) -> dict[int, tuple[str, str | None]]:
        """`{id: (path, rel_path)}` as stored, unverified (what a damaged row says it is)."""
        ...

    def has_poses(self) -> bool:
        """Whether any stored scan has a pose."""
        ...

    def existing(self, paths: Iterable[str]) -> set[str]:
        """Which of `paths` are stored already (for resuming a build)."""
        ...

    def size_bytes(self) -> int:
        """The map's size in bytes where this process can see it (0 on a server)."""
        ...

    def signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(ids [N], signatures [N, D] float32)` of the sound scans in id order; the
        damaged are left out (recorded); an empty map or none sound: `DatabaseError`."""
        ...

    def side_signatures(self) -> tuple[np.ndarray, np.ndarray]:
        """`(scan ids [M], signatures [M, D])` of the sound side views (none: empty)."""
        ...

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """`(poses [N, 4] x, y, z, yaw, times [N])` in id order; NaN unknown or damaged."""
        ...

    def rows(self, ids: Sequence[int] | np.ndarray) -> MatchRows:
        """Paths, poses and features of the scans `ids`, in that order; any damaged or
        missing: `DamagedRows` naming them (recorded), nothing returned."""
        ...

    def check(self) -> list[str]:
        """Every problem of the map, one line each ([] when sound); fills `damaged`."""
        ...

    def index_for(self, kind: str = "auto", note: Any = None) -> tuple[np.ndarray, Any]:
        """`(ids, index)` to search the map's signatures with (`exact`, `ann` or `auto`)."""
        ...


class StoreBase:
    """What both stores do without touching their storage: read the record out of the
    meta, refuse another model or a batch of another shape, decode and verify a scan's
    feature blob, say what a migration did. The store sets `path` and calls
    `_take_meta`; it implements `close`."""

    path: Any
    migrated: tuple[int, int] | None = None
    migration_backup: Path | None = None
    read_only: str | None = None

    def _take_meta(self, meta: dict[str, str]) -> None:
        """What every store reads from its meta (checked before it is opened): the
        format, the model, the signature and feature sizes, the side views; no row
        damaged yet."""
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
        # Stored size of one scan's (inflated) float16 features.
        self._nfeat = int(np.prod(self.feature_shape)) * _FEAT_DTYPE.itemsize
        self.damaged: dict[int, str] = {}
        try:
            offsets = json.loads(meta.get("side_views_m", "[]"))
            self.side_offsets: tuple[float, ...] = tuple(float(o) for o in offsets)
        except (ValueError, TypeError):
            raise DatabaseError(self.path, "corrupt database: unreadable side_views_m") from None

    @property
    def checksummed(self) -> bool:
        """Whether rows carry checksums (format 2); a format-1 map's rows are unverified."""
        return self.format_version >= 2

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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

    # -- checks -----------------------------------------------------------------

    def check_model(self, model: ModelInfo) -> None:
        """Refuse a model or BEV configuration other than the one that built this map."""
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
        """Refuse a batch whose signatures, features or side views the map cannot hold."""
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

            def said(offsets: tuple[float, ...]) -> str:
                return f"side views at {side_views_m(offsets):g} m" if offsets else "no side views"

            raise DatabaseError(
                self.path,
                f"holds {said(self.side_offsets)}, got scans with {said(batch.side_offsets)}; "
                "add them with the map's --side-views setting or build a new map",
            )
        if batch.side_offsets and batch.side_signatures.shape[2] != self.signature_dim:  # type: ignore[union-attr]
            raise DatabaseError(self.path, "side view signatures have another dimension")

    # -- rows -----------------------------------------------------------------------

    def _note_damaged(self, bad: dict[int, str], names: dict[int, str]) -> None:
        for rid in bad:
            self.damaged[int(rid)] = names.get(rid, "?")

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


# -- which store ------------------------------------------------------------------------


def store_class(path: Any) -> type[MapStore]:
    """`MilvusDatabase` for a `milvus:` address, else `Database` (an SQLite file)."""
    # deferred: both stores import this module (their protocol and base)
    from disco_cli.maps.database import Database
    from disco_cli.maps.milvus_store import MilvusDatabase

    return MilvusDatabase if parse_address(path) is not None else Database


def open_store(path: Any, **kwargs: Any) -> MapStore:
    """The map at `path` opened by its store (`MapStore.open`'s keywords)."""
    return store_class(path).open(path, **kwargs)
