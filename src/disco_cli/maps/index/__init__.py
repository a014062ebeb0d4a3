"""Which signature index answers a map's searches: exact, or approximate for big maps.

Every index has `SignatureIndex.search`'s contract: `search(queries, k, limit=None,
exclude=None) -> (rows [B, k] int64, distances [B, k] float64)`, rows padded with -1.

- `exact`: `search.SignatureIndex`, built from the map's signatures at the first query.
- `ann`: an inverted-file index of 8-bit codes from faiss (`index/ann.py`; the optional
  extra `pip install 'disco-cli[ann]'`), kept in a sidecar file beside the map
  (`map.db.ann`) and rebuilt when the map changed since it was written.
- `auto` (the default): `ann` from `AUTO_ANN_MIN_ROWS` scans when faiss is installed,
  else `exact`.

Why 200,000: below it the exact search is already fast enough (about 5 ms per query at
100k scans on the 2-core EPYC, docs/benchmarks.md) and holds every answer exactly, while
the approximate index costs minutes to build and loses some recall; above it the exact
search grows past 5 ms and 1 GB and keeps growing linearly (27 ms and 5 GB at 1M).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.maps.map_side_views import index_for

__all__ = [
    "INDEX_KINDS",
    "AUTO_ANN_MIN_ROWS",
    "INSTALL_HINT",
    "ann_available",
    "check_index_kind",
    "choose_kind",
    "map_key",
    "sidecar_path",
    "index_for_database",
]

INDEX_KINDS = ("auto", "exact", "ann")
AUTO_ANN_MIN_ROWS = 200_000
INSTALL_HINT = "the approximate index needs faiss: pip install 'disco-cli[ann]'"


def ann_available() -> bool:
    """Whether the optional extra (faiss) is installed (and imports)."""
    try:
        import faiss  # noqa: F401  # deferred: optional extra
    except ImportError:
        return False
    return True


def check_index_kind(kind: str) -> str:
    if kind not in INDEX_KINDS:
        raise DiscoError(f"--index: one of {', '.join(INDEX_KINDS)}, got {kind!r}")
    return kind


def choose_kind(kind: str, rows: int, note: Any = None) -> str:
    """`exact` or `ann` for a map of `rows` scans. `ann` without faiss is one
    `DiscoError`; `auto` falls back to exact, with one `note` above the threshold."""
    check_index_kind(kind)
    if kind == "ann" and not ann_available():
        raise DiscoError(INSTALL_HINT)
    if kind != "auto":
        return kind
    if rows < AUTO_ANN_MIN_ROWS:
        return "exact"
    if ann_available():
        return "ann"
    if note is not None:
        note(f"{rows} scans: the exact search is slow at this size; {INSTALL_HINT}")
    return "exact"


def map_key(db: Any) -> dict[str, Any]:
    """What says whether a sidecar index still describes the map `db`: the number of
    scans, the largest scan id (ids only grow: an append changes both), the map's
    `generation` (every write raises it: a repair rewrites rows without changing the
    other two) and the model."""
    n = len(db)
    return {
        "rows": int(n),
        "max_id": int(db.next_id()) - 1,
        "generation": int(db.generation),
        "fingerprint": db.model.fingerprint,
        "side_views_m": list(db.side_offsets),
    }


def sidecar_path(db_path: str | Path) -> Path:
    """Where the approximate index of the map `db_path` is kept: `map.db.ann`."""
    p = Path(db_path)
    return p.with_name(p.name + ".ann")


def index_for_database(db: Any, kind: str = "auto", note: Any = None) -> tuple[np.ndarray, Any]:
    """`(ids, index)` to search the map `db` with (`side_views.index_for` for `exact`;
    for `ann`, the sidecar when it is current, else one built and saved beside the map).
    `note(message)` is told when an index is built or a sidecar is unusable."""
    chosen = choose_kind(kind, len(db), note)
    if chosen == "exact":
        return index_for(db)
    # deferred: ann.py imports this module; only --index ann (faiss) needs it
    from disco_cli.maps.index.ann import open_or_build

    return open_or_build(db, note=note)
