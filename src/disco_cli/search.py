"""Exact top-k search over signatures, and matching a query against a map database.

Distances are Euclidean. The bulk of the work is one BLAS matrix product
(`||q||^2 - 2 q.d + ||d||^2`) in float32; that expansion can misorder distances
that differ by less than its rounding error, so every candidate within a proven
error bound of the k-th distance is re-measured directly in float64 before the
final order is taken (ties broken by row). The result is the same as a plain
float64 brute force.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SignatureIndex", "Match", "brute_force_topk", "match_queries"]

_EPS32 = float(np.finfo(np.float32).eps)
# Cap on the [rows, queries] float32 distance block, in elements (64 MiB).
_BLOCK_ELEMS = 16 * 1024 * 1024


def brute_force_topk(signatures: np.ndarray, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference: float64 distances to every row, stable sort. For tests and benchmarks."""
    d = np.sqrt(((np.asarray(signatures, np.float64) - np.asarray(query, np.float64)) ** 2).sum(1))
    order = np.argsort(d, kind="stable")[:k]
    return order, d[order]


class SignatureIndex:
    """Signatures `[N, D]` held once as one float32 matrix, searched exactly.

    `search` takes, per query, an optional `limit` (only rows `< limit` count, for
    online loop detection) and an optional boolean `exclude` mask over rows. Besides
    the matrix it holds one float32 norm per row.
    """

    def __init__(self, signatures: np.ndarray):
        sig = np.asarray(signatures)
        if sig.ndim != 2:
            raise ValueError(f"signatures must be [N, D], got {sig.shape}")
        # No copy when the caller hands over a C-contiguous float32 matrix.
        self.matrix = np.ascontiguousarray(sig, dtype=np.float32)
        if not np.isfinite(self.matrix).all():
            raise ValueError("signatures must be finite")
        self.sq_norms = np.einsum("ij,ij->i", self.matrix, self.matrix, dtype=np.float32)
        self._max_norm = float(np.sqrt(self.sq_norms.max())) if len(self.matrix) else 0.0

    def __len__(self) -> int:
        return len(self.matrix)

    @property
    def dim(self) -> int:
        return self.matrix.shape[1]

    def search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Top-k rows and distances per query: `(rows [B, k] int64, distances [B, k] float64)`.

        Where fewer than k rows are allowed, the tail is padded with row -1, distance inf.
        """
        q = np.asarray(queries, dtype=np.float32)
        single = q.ndim == 1
        q = np.ascontiguousarray(np.atleast_2d(q))
        if q.shape[1] != self.dim:
            raise ValueError(f"queries must be [B, {self.dim}], got {q.shape}")
        if not np.isfinite(q).all():
            raise ValueError("queries must be finite")
        b, n = len(q), len(self.matrix)
        if limit is not None:
            limit = np.broadcast_to(np.asarray(limit, dtype=np.int64), (b,))
        if exclude is not None:
            exclude = np.asarray(exclude, dtype=bool)
            if exclude.ndim == 1:
                exclude = np.broadcast_to(exclude, (b, n))
            if exclude.shape != (b, n):
                raise ValueError(f"exclude must be [{b}, {n}], got {exclude.shape}")
        rows = np.full((b, k), -1, dtype=np.int64)
        dists = np.full((b, k), np.inf)
        if k <= 0 or n == 0:
            return (rows[0], dists[0]) if single else (rows, dists)
        step = max(1, _BLOCK_ELEMS // max(n, 1))
        for s in range(0, b, step):
            qs = q[s:s + step]
            # [n, bs]: one BLAS call for the whole block of queries (a matrix-vector
            # product for one query).
            dots = self.matrix @ qs[0] if len(qs) == 1 else self.matrix @ qs.T
            dots = dots.reshape(n, len(qs))
            for j in range(len(qs)):
                i = s + j
                lim = n if limit is None else int(min(max(limit[i], 0), n))
                ex = None if exclude is None else exclude[i, :lim]
                r, d = self._topk(q[i], dots[:lim, j], lim, k, ex)
                rows[i, :len(r)] = r
                dists[i, :len(d)] = d
        return (rows[0], dists[0]) if single else (rows, dists)

    def _exact(self, q: np.ndarray, cand: np.ndarray) -> np.ndarray:
        diff = self.matrix[cand].astype(np.float64) - q.astype(np.float64)
        return np.einsum("ij,ij->i", diff, diff)

    def _topk(
        self, q: np.ndarray, dots: np.ndarray, lim: int, k: int, exclude: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        if lim == 0:
            return np.empty(0, np.int64), np.empty(0)
        q_sq = float(np.dot(q, q))
        approx = self.sq_norms[:lim] - 2.0 * dots
        approx += np.float32(q_sq)
        valid = lim
        if exclude is not None:
            approx[exclude] = np.inf
            valid -= int(np.count_nonzero(exclude))
        kk = min(k, valid)
        if kk <= 0:
            return np.empty(0, np.int64), np.empty(0)
        part = np.argpartition(approx, kk - 1)[:kk] if kk < lim else np.arange(lim)
        kth = float(approx[part][np.isfinite(approx[part])].max())
        # Worst-case rounding: D*eps*|q||d| for a float32 dot product of length D, and
        # eps*(|q| + |d|)^2 for the float32 sums. Whatever lies within twice that of the
        # k-th is re-measured exactly.
        qn = np.sqrt(q_sq)
        tol = 2.0 * (2.0 * self.dim * _EPS32 * qn * self._max_norm
                     + 4.0 * _EPS32 * (qn + self._max_norm) ** 2) + 1e-30
        cand = np.flatnonzero(approx <= kth + tol)
        exact = self._exact(q, cand)
        order = np.lexsort((cand, exact))[:kk]
        return cand[order], np.sqrt(exact[order])


@dataclass
class Match:
    """One match of a query in a database."""

    rank: int  # 1-based
    row: int  # row in the index (0-based, id order)
    match_id: int
    path: str
    distance: float
    yaw_deg: float
    pose: np.ndarray  # x, y, z, yaw (rad) of the match, NaN where unknown


def match_queries(
    index: SignatureIndex,
    ids: np.ndarray,
    db: Any,
    model: Any,
    signatures: np.ndarray,
    features: np.ndarray,
    k: int,
    limit: Sequence[int] | np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    max_distance: float | None = None,
) -> list[list[Match]]:
    """Top-k matches of each query with their yaw: signature search, then the model's
    `rerank` hook when it asks for one (Scan Context), then yaw from the stored features
    of the top rows only. `db` is a `Database` (anything with `rows(ids)`)."""
    rerank_n = int(getattr(model, "rerank_candidates", 0) or 0)
    wide = max(k, rerank_n) if rerank_n > 0 else k
    rows, dists = index.search(signatures, wide, limit=limit, exclude=exclude)
    out: list[list[Match]] = []
    for i in range(len(rows)):
        keep = rows[i] >= 0
        r, d = rows[i][keep], dists[i][keep]
        if len(r) == 0:
            out.append([])
            continue
        stored = db.rows(ids[r])
        if rerank_n > 0:
            d_new, yaw = model.rerank(features[i], stored.features)
            d_new = np.asarray(d_new, dtype=np.float64)
            yaw = np.asarray(yaw, dtype=np.float64)
            order = np.lexsort((r, d_new))[:k]
            r, d, yaw = r[order], d_new[order], yaw[order]
            sel = order
        else:
            sel = np.arange(len(r))
            yaw = None
        if max_distance is not None:
            ok = d <= max_distance
            r, d, sel = r[ok], d[ok], sel[ok]
            if yaw is not None:
                yaw = yaw[ok]
        if len(r) and yaw is None:
            yaw = np.asarray(model.yaw(features[i], stored.features[sel]), dtype=np.float64)
        out.append([
            Match(
                rank=j + 1,
                row=int(r[j]),
                match_id=int(stored.ids[sel[j]]),
                path=stored.paths[sel[j]],
                distance=float(d[j]),
                yaw_deg=float(yaw[j]),
                pose=stored.poses[sel[j]],
            )
            for j in range(len(r))
        ])
    return out
