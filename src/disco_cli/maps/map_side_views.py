"""Map side views: map scans seen again from a few metres to their left and right, stored
in the map (not the query views of `query_views.py`).

A later visit rarely drives the map's exact line. Recall falls with the lateral
distance to the nearest map scan (issue 12: from 1.00 at 2-3 m to 0.61 at 3-4 m on
the hard set), because a polar BEV changes with the sensor's position even where the
scene does not. So a map can store, for each scan, the signatures of the same points
re-centred on a virtual sensor `offset` metres along the scan's own y axis (left and
right of the vehicle). They take part in the signature search only: a view that wins
stands for its scan, and re-ranking, yaw and relative pose use the scan itself.

The views come from the scan's own points (no other scan, no ground truth), so the
occlusions are those seen from the real sensor: a view is an approximation that only
has to bring the right scan into the top candidates. Their BEVs are made with the
scan's own, in the embedding stage (`embedding/load.py`, `side_view_bevs`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from disco_cli.maps.signature_index import SignatureIndex

__all__ = [
    "side_offsets",
    "side_views_m",
    "ViewIndex",
    "index_for",
]


def side_offsets(metres: float) -> tuple[float, ...]:
    """The offsets stored for `--side-views METRES`: none for 0, else left and right."""
    m = float(metres)
    if not np.isfinite(m) or m < 0:
        raise ValueError(f"side views: the offset must be a finite number >= 0, got {metres}")
    return () if m == 0 else (m, -m)


def side_views_m(offsets: Sequence[float]) -> float:
    """The M of `--side-views M` that gave `offsets` (0: none)."""
    return max((abs(float(o)) for o in offsets), default=0.0)


class ViewIndex:
    """A signature search over scans and their side views that answers in scans.

    `search` has `SignatureIndex.search`'s contract over the scans' rows: each scan
    appears at most once, at the distance of its closest signature (its own or a
    view's); `limit` and `exclude` refer to scan rows.
    """

    def __init__(self, signatures: np.ndarray, view_owner: np.ndarray, view_signatures: np.ndarray):
        self.n_scans = len(signatures)
        owner = np.asarray(view_owner, dtype=np.int64).reshape(-1)
        if len(owner) != len(view_signatures):
            raise ValueError("one owner row per view signature")
        if len(owner) and (owner.min() < 0 or owner.max() >= self.n_scans):
            raise ValueError("a view's owner row is out of range")
        self.owner = np.concatenate([np.arange(self.n_scans, dtype=np.int64), owner])
        views_per_scan = np.bincount(owner, minlength=self.n_scans) if len(owner) else None
        self.most_views = 0 if views_per_scan is None else int(views_per_scan.max())
        both = np.concatenate([np.asarray(signatures, np.float32), view_signatures], axis=0)
        self._index: Any = SignatureIndex(both)

    @classmethod
    def over(cls, inner: Any, n_scans: int, view_owner: np.ndarray) -> ViewIndex:
        """A `ViewIndex` over an index built elsewhere (the approximate index of
        `index/ann.py`) whose rows are the `n_scans` scans, then views of `view_owner`."""
        view = cls.__new__(cls)
        owner = np.asarray(view_owner, dtype=np.int64).reshape(-1)
        if len(inner) != n_scans + len(owner):
            raise ValueError("the index must hold the scans, then their views")
        view.n_scans = n_scans
        view.owner = np.concatenate([np.arange(n_scans, dtype=np.int64), owner])
        counts = np.bincount(owner, minlength=n_scans) if len(owner) else None
        view.most_views = 0 if counts is None else int(counts.max())
        view._index = inner
        return view

    def __len__(self) -> int:
        return self.n_scans

    def append(self, signatures: np.ndarray, view_signatures: np.ndarray | None = None) -> None:
        """Add scans `[m, D]` (rows n, n + 1, ...) with their views `[m, V, D]`, if any
        (online loop detection grows the index one scan at a time)."""
        sig = np.atleast_2d(np.asarray(signatures, dtype=np.float32))
        m = len(sig)
        rows = [sig]
        owners = [np.arange(self.n_scans, self.n_scans + m, dtype=np.int64)]
        if view_signatures is not None and np.size(view_signatures):
            views = np.asarray(view_signatures, dtype=np.float32).reshape(m, -1, sig.shape[1])
            rows.append(views.reshape(-1, sig.shape[1]))
            owners.append(np.repeat(owners[0], views.shape[1]))
            self.most_views = max(self.most_views, views.shape[1])
        self._index.append(np.concatenate(rows))
        self.owner = np.concatenate([self.owner, *owners])
        self.n_scans += m

    @property
    def dim(self) -> int:
        return self._index.dim

    def search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        return self._search(self._index.search, queries, k, limit, exclude)

    def approximate_search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`search` by the inner index's `approximate_search` (candidates only)."""
        return self._search(self._index.approximate_search, queries, k, limit, exclude)

    def _search(
        self,
        inner_search: Any,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None,
        exclude: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(queries, dtype=np.float32)
        single = q.ndim == 1
        q = np.atleast_2d(q)
        b, n = len(q), self.n_scans
        # A scan's rows are allowed iff the scan is: limits become a mask over all rows.
        mask = None
        if limit is not None or exclude is not None:
            allowed = np.ones((b, n), dtype=bool)
            if limit is not None:
                lim = np.broadcast_to(np.asarray(limit, dtype=np.int64), (b,))
                allowed &= np.arange(n)[None, :] < lim[:, None]
            if exclude is not None:
                allowed &= ~np.broadcast_to(np.asarray(exclude, dtype=bool), (b, n))
            mask = ~allowed[:, self.owner]
        # Deep enough that k distinct scans survive even when every one of them
        # comes back with all its views.
        deep = max(k, 0) * (1 + self.most_views)
        rows, dists = inner_search(q, deep, exclude=mask)
        out_r = np.full((b, max(k, 0)), -1, dtype=np.int64)
        out_d = np.full((b, max(k, 0)), np.inf)
        for i in range(b):
            keep = rows[i] >= 0
            scans = self.owner[rows[i][keep]]
            _, first = np.unique(scans, return_index=True)
            first = np.sort(first)[:k]  # rows come sorted by distance: keep each scan's best
            out_r[i, : len(first)] = scans[first]
            out_d[i, : len(first)] = dists[i][keep][first]
        return (out_r[0], out_d[0]) if single else (out_r, out_d)


def index_for(db: Any) -> tuple[np.ndarray, Any]:
    """`(ids, index)` to search a database with: a `ViewIndex` when it stores side
    views, else a plain `SignatureIndex`."""
    ids, sigs = db.signatures()
    if not db.side_offsets:
        return ids, SignatureIndex(sigs)
    owner_ids, view_sigs = db.side_signatures()
    owner_rows = np.searchsorted(ids, owner_ids)
    known = (owner_rows < len(ids)) & (ids[np.minimum(owner_rows, len(ids) - 1)] == owner_ids)
    return ids, ViewIndex(sigs, owner_rows[known], view_sigs[known])
