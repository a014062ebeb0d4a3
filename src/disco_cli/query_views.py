"""Looking beside the query: the candidates its side views find (`DiscoModel.query_views`).

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
    nearest = order[at]  # each scan once, at its nearest
    nearest = nearest[np.lexsort((r[nearest], d[nearest]))]
    top = np.zeros(len(nearest), bool)
    top[:first] = True
    in_first = top | np.isin(r[nearest], rows[:first])
    rest = ~in_first & np.isin(r[nearest], rows)
    kept = np.concatenate([nearest[in_first], nearest[rest]])
    return r[kept], d[kept], int(in_first.sum())


def views_search(
    index: Any, view_signatures: np.ndarray, k: int, limit: Any = None, exclude: Any = None
) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest map scans [V, k] of each of one query's views [V, D], by the
    index's `approximate_search` where it has one (a view only proposes candidates,
    which are then re-ranked), else its exact `search`. `limit` and `exclude` are the
    query's own (a row limit, a mask over rows), which the indexes apply to every view."""
    search = getattr(index, "approximate_search", index.search)
    return search(np.asarray(view_signatures, np.float32), k, limit=limit, exclude=exclude)


# The views' first pass on large maps: the signatures projected on their leading
# principal axes. A view only proposes candidates (re-measured exactly, then re-ranked),
# so an approximate pass serves, and six exact searches of a 10,000-scan map would cost
# more than the rest of the query.
PROJECTED_DIMS = 96
# Each view keeps this many times the asked-for rows by projected distance, then the
# nearest of those by exact distance.
PROJECTED_WIDEN = 4
# The principal axes come from at most this many rows, evenly spaced over the map.
PROJECTED_SAMPLE = 2048


class ProjectedSignatures:
    """Map signatures [N, D] on their PROJECTED_DIMS leading principal axes (float32,
    one pass of a randomized SVD on a sample of rows): approximate nearest rows for a
    batch of queries in one small matrix product, then exact distances for those."""

    def __init__(self, matrix: np.ndarray, dims: int = PROJECTED_DIMS, seed: int = 0):
        self.matrix = matrix
        n, d = matrix.shape
        sample = matrix[np.linspace(0, n - 1, min(n, PROJECTED_SAMPLE)).astype(np.int64)]
        self.mean = sample.mean(axis=0, dtype=np.float64).astype(np.float32)
        x = sample - self.mean
        dims = max(1, min(dims, d, len(x)))
        # Randomized range finder with one power iteration (Halko et al.), float32.
        omega = np.random.default_rng(seed).standard_normal((d, dims + 16)).astype(np.float32)
        y = x @ (x.T @ (x @ omega))
        q, _ = np.linalg.qr(y)
        _, _, vt = np.linalg.svd(q.T @ x, full_matrices=False)
        self.axes = np.ascontiguousarray(vt[:dims].T, dtype=np.float32)  # [D, p]
        # (x - mean) A and |x - mean|^2 without a centred copy of the map.
        projected = matrix @ self.axes - self.mean @ self.axes  # [N, p]
        # Each row's squared norm off the axes joins its projected one: the distance
        # estimate is then |pq - px|^2 + |rx|^2 (+ the query's own residual, the same
        # for every row), closer to the true one than the projection alone.
        m64 = self.mean.astype(np.float64)
        centred_sq = (
            np.einsum("ij,ij->i", matrix, matrix, dtype=np.float64)
            - 2.0 * (matrix @ self.mean).astype(np.float64)
            + m64 @ m64
        )
        self.sq = centred_sq.astype(np.float32)
        self.projected_t = np.ascontiguousarray(projected.T)  # [p, N]: one GEMM per batch

    def search(
        self, queries: np.ndarray, k: int, limit: Any = None, exclude: Any = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Approximate top-k rows and exact distances [B, k] (padded with -1, inf)."""
        q = np.atleast_2d(np.asarray(queries, np.float32))
        b, n = len(q), len(self.matrix)
        pq = (q - self.mean) @ self.axes
        approx = pq @ self.projected_t  # [B, N]: the distance less |pq|^2, per row
        approx *= -2.0
        approx += self.sq
        if limit is not None:
            lim = np.broadcast_to(np.asarray(limit, np.int64), (b,))
            approx[np.arange(n)[None] >= lim[:, None]] = np.inf
        if exclude is not None:
            approx[np.broadcast_to(np.asarray(exclude, bool), (b, n))] = np.inf
        wide = min(n, max(k, 0) * PROJECTED_WIDEN)
        rows = np.full((b, max(k, 0)), -1, np.int64)
        dists = np.full((b, max(k, 0)), np.inf)
        if wide == 0:
            return rows, dists
        cand = np.argpartition(approx, wide - 1, axis=1)[:, :wide]  # [B, wide]
        ok = np.isfinite(np.take_along_axis(approx, cand, axis=1))
        diff = self.matrix[cand] - q[:, None]  # [B, wide, D]
        exact = np.sqrt(np.einsum("bkd,bkd->bk", diff, diff)).astype(np.float64)
        exact[~ok] = np.inf
        for i in range(b):
            o = np.lexsort((cand[i], exact[i]))[:k]
            o = o[np.isfinite(exact[i, o])]
            rows[i, : len(o)], dists[i, : len(o)] = cand[i, o], exact[i, o]
        return rows, dists
