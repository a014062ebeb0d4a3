"""Query views: the candidates that the query, re-centred to either side, finds
(`model.query_views`; not the map's side views of `map_side_views.py`).

A revisit 4-8 m beside the map's route sees the street from a place no map scan was
taken: its signature is far from all of them, and none of the nearest re-ranks well.
The query's feature images re-centred a few metres to either side stand where the
map's sensor may have stood. On every query their signatures are searched beside the
query's own, each map scan counting at its nearest over the query and its views; the
query's own candidates all stay (its first ones in the first pass), so the views add
places and never push one out of the re-ranking.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def candidates_with_views(
    rows: np.ndarray,
    dists: np.ndarray,
    view_rows: np.ndarray,
    view_dists: np.ndarray,
    first: int,
) -> tuple[np.ndarray, np.ndarray, int]:
    """A query's candidate rows and signature distances [W] with its views' finds, and
    how many of them the first re-ranking pass takes.

    `rows`, `dists` [N]: the query's own nearest map scans, nearest first; `view_rows`,
    `view_dists`: what its views found (any shape, -1 for none). Each scan counts at its
    nearest over the query and its views. The candidates are every one of `rows` and
    the views' scans among the `first` nearest so. The first pass holds the `first`
    nearest over all and the query's own `first`: a view never pushes out a scan the
    query's own search put first. Rows come first pass first, each part ordered by
    that nearest distance (ties by row)."""
    r = np.concatenate([np.ravel(rows), np.ravel(view_rows)]).astype(np.int64)
    d = np.concatenate([np.ravel(dists), np.ravel(view_dists)]).astype(np.float64)
    found = r >= 0
    r, d = r[found], d[found]
    order = np.lexsort((r, d))
    _, at = np.unique(r[order], return_index=True)
    # Each scan once, at its nearest: its first place in `order`, which is already
    # by (distance, row), so those places in turn keep that order.
    nearest = order[np.sort(at)]
    own = np.sort(np.asarray(rows, np.int64))
    own_first = np.sort(np.asarray(rows, np.int64)[:first])
    top = np.zeros(len(nearest), bool)
    top[:first] = True
    in_first = top | _member(r[nearest], own_first)
    rest = ~in_first & _member(r[nearest], own)
    kept = np.concatenate([nearest[in_first], nearest[rest]])
    return r[kept], d[kept], int(in_first.sum())


def _member(values: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """Whether each of `values` is in `sorted_set` (ascending): np.isin for a few
    dozen rows, without its set-up."""
    if len(sorted_set) == 0:
        return np.zeros(len(values), bool)
    at = np.minimum(np.searchsorted(sorted_set, values), len(sorted_set) - 1)
    return sorted_set[at] == values


def views_search(
    index: Any,
    view_signatures: np.ndarray,
    k: int,
    approximate: bool,
    limit: Any = None,
    exclude: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest map scans [V, k] of each of one query's views [V, D], by the
    index's `approximate_search` when `approximate` (a view only proposes candidates,
    which are then re-ranked; `QueryPolicy.approximate_views_from`), else its exact
    `search`. `limit` and `exclude` are the query's own (a row limit, a mask over
    rows), which the indexes apply to every view."""
    # An index without an approximate search (a remote store's) answers exactly.
    search = getattr(index, "approximate_search", index.search) if approximate else index.search
    return search(np.asarray(view_signatures, np.float32), k, limit=limit, exclude=exclude)
