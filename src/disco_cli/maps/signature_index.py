"""Exact top-k search over signatures (the map side of a query; `search.py` is the query
stage that uses it).

Distances are Euclidean; the result is the same as a plain float64 brute force
(ties broken by row). Two first passes find the rows that can be in the top k, and
those are re-measured directly in float64 (`exact_topk`: the compiled core reads them
in place, `src/cpp/disco/exact_search.hpp`):

- small maps: one BLAS matrix product (`||q||^2 - 2 q.d + ||d||^2`) in float32, and
  every row within a proven rounding bound of the k-th is re-measured;
- large maps (from `int8_min_rows` rows): an int8 copy of the signatures (a quarter
  of their bytes) scanned by the compiled core, which bounds every row's distance by
  its quantization error (`src/cpp/disco/int8_search.hpp`) and returns the rows whose
  lower bound is at most the k-th smallest upper bound. Reading a quarter of the
  bytes is what makes a 100k-scan search fast: the float32 scan is bound by memory
  bandwidth.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from disco_cli.runtime.threads import get_threads

__all__ = [
    "SignatureIndex",
    "ProjectedSignatures",
    "brute_force_topk",
    "checked_queries",
    "exact_topk",
]

_EPS32 = float(np.finfo(np.float32).eps)
# Cap on the [rows, queries] float32 distance block, in elements (64 MiB).
_BLOCK_ELEMS = 16 * 1024 * 1024
# From this many rows the int8 codes are made and scanned first (lowered from 16,384 in
# commit dd3226c, with bench_query.py). The answer is exact either way: only the time
# differs. The query policy's `approximate_views_from` is the same size by default.
INT8_MIN_ROWS = 4096


def brute_force_topk(
    signatures: np.ndarray, query: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Reference: float64 distances to every row, stable sort. For tests and benchmarks."""
    d = np.sqrt(((np.asarray(signatures, np.float64) - np.asarray(query, np.float64)) ** 2).sum(1))
    order = np.argsort(d, kind="stable")[:k]
    return order, d[order]


def checked_queries(queries: np.ndarray, dim: int) -> tuple[np.ndarray, bool]:
    """Queries as a C-contiguous float32 [B, dim] matrix, and whether one [dim] vector
    was given; ValueError for another width or a value that is not finite."""
    q = np.asarray(queries, dtype=np.float32)
    single = q.ndim == 1
    q = np.ascontiguousarray(np.atleast_2d(q))
    if q.shape[1] != dim:
        raise ValueError(f"queries must be [B, {dim}], got {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("queries must be finite")
    return q, single


class SignatureIndex:
    """Signatures `[N, D]` held once as one float32 matrix, searched exactly.

    `search` takes, per query, an optional `limit` (only rows `< limit` count, for
    online loop detection) and an optional boolean `exclude` mask over rows. Besides
    the matrix it holds one float32 norm per row.
    """

    def __init__(
        self, signatures: np.ndarray, int8_min_rows: int = INT8_MIN_ROWS, threads: int | None = None
    ):
        sig = np.asarray(signatures)
        if sig.ndim != 2:
            raise ValueError(f"signatures must be [N, D], got {sig.shape}")
        # No copy when the caller hands over a C-contiguous float32 matrix.
        self.matrix = np.ascontiguousarray(sig, dtype=np.float32)
        # A NaN or an infinity anywhere in a row makes its float64 squared norm non-finite.
        sq64 = np.einsum("ij,ij->i", self.matrix, self.matrix, dtype=np.float64)
        if not np.isfinite(sq64).all():
            raise ValueError("signatures must be finite")
        self.sq_norms = sq64.astype(np.float32)
        self._max_norm = float(np.sqrt(self.sq_norms.max())) if len(self.matrix) else 0.0
        # None (or 0): disco's thread setting (disco_cli/runtime/threads.py), read once.
        self.threads = threads if threads else get_threads()
        self._codes: _Int8Codes | None = None
        self._projected: Any = None  # approximate_search's, made on first use
        self._spare: tuple[np.ndarray, np.ndarray] | None = None  # growth room (append)
        if len(self.matrix) >= max(int8_min_rows, 1) and _Int8Codes.available():
            self._codes = _Int8Codes(self.matrix, sq64)

    def __len__(self) -> int:
        return len(self.matrix)

    def append(self, signatures: np.ndarray) -> None:
        """Add rows at the end (online loop detection grows its index one scan at a
        time). Storage doubles as it grows; the int8 pre-scan is dropped, since its codes
        cover a fixed set of rows (results are the same exact ones without it)."""
        new = np.ascontiguousarray(np.atleast_2d(np.asarray(signatures)), dtype=np.float32)
        if new.ndim != 2 or new.shape[1] != self.dim:
            raise ValueError(f"signatures must be [B, {self.dim}], got {new.shape}")
        sq64 = np.einsum("ij,ij->i", new, new, dtype=np.float64)
        if not np.isfinite(sq64).all():
            raise ValueError("signatures must be finite")
        n, need = len(self.matrix), len(self.matrix) + len(new)
        if self._spare is None or need > len(self._spare[0]):
            cap = max(need, 2 * n, 64)
            mat = np.empty((cap, self.dim), np.float32)
            sq = np.empty(cap, np.float32)
            mat[:n], sq[:n] = self.matrix, self.sq_norms
            self._spare = (mat, sq)
        mat, sq = self._spare
        mat[n:need], sq[n:need] = new, sq64
        self.matrix, self.sq_norms = mat[:need], sq[:need]
        if len(new):
            self._max_norm = max(self._max_norm, float(np.sqrt(sq64.max())))
        self._codes = self._projected = None

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
        q, single = checked_queries(queries, self.dim)
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
            qs = q[s : s + step]
            dots = None
            if self._codes is None:
                # [n, bs]: one BLAS call for the whole block of queries (a matrix-vector
                # product for one query).
                dots = self.matrix @ qs[0] if len(qs) == 1 else self.matrix @ qs.T
                dots = dots.reshape(n, len(qs))
            for j in range(len(qs)):
                i = s + j
                lim = n if limit is None else int(min(max(limit[i], 0), n))
                ex = None if exclude is None else exclude[i, :lim]
                if dots is None:
                    r, d = self._topk_int8(q[i], lim, k, ex)
                else:
                    r, d = self._topk(q[i], dots[:lim, j], lim, k, ex)
                rows[i, : len(r)] = r
                dists[i, : len(d)] = d
        return (rows[0], dists[0]) if single else (rows, dists)

    def approximate_search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`search` for candidates only (a query's views, `query_views.py`): the nearest
        by projected signatures (`ProjectedSignatures`, made on the first call)
        re-measured exactly, which may miss a true neighbour. An index grown by `append`
        answers with `search` itself: a projection would go stale with every row."""
        if self._spare is not None:
            return self.search(queries, k, limit=limit, exclude=exclude)
        if self._projected is None:
            self._projected = ProjectedSignatures(self.matrix)
        q, _ = checked_queries(queries, self.dim)
        return self._projected.search(q, k, limit=limit, exclude=exclude)

    def _topk_int8(
        self, q: np.ndarray, lim: int, k: int, exclude: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        assert self._codes is not None
        cand = self._codes.candidates(q, k, lim, exclude, self.threads)
        if len(cand) == 0:
            return np.empty(0, np.int64), np.empty(0)
        if len(cand) > max(INT8_MIN_ROWS, lim // 8):
            # Signatures closer together than their int8 error: the bounds prune little,
            # and the float32 product is then cheaper than re-measuring so many rows.
            return self._topk(q, self.matrix[:lim] @ q, lim, k, exclude)
        return _nearest(self.matrix, q, cand, k)

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
        tol = (
            2.0
            * (
                2.0 * self.dim * _EPS32 * qn * self._max_norm
                + 4.0 * _EPS32 * (qn + self._max_norm) ** 2
            )
            + 1e-30
        )
        return _nearest(self.matrix, q, np.flatnonzero(approx <= kth + tol), kk)


def exact_topk(
    matrix: np.ndarray, queries: np.ndarray, cand: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per query (float32 [B, D]), the k nearest of its candidate rows of `matrix`
    (int64 [B, M], -1 for none) by float64 distance, ties by row: `(rows [B, k],
    distances [B, k])`, padded with -1 and inf. The compiled core reads the rows in
    place (`src/cpp/disco/exact_search.hpp`); without it, NumPy does the same."""
    try:
        from disco_cli import _core  # deferred: looked up at each call: tests replace it

        kernel = _core.exact_topk
    except (ImportError, AttributeError):
        return _exact_topk_numpy(matrix, queries, cand, k)
    return kernel(matrix, queries, cand, int(k))


def _exact_topk_numpy(
    matrix: np.ndarray, queries: np.ndarray, cand: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    rows = np.full((len(queries), max(k, 0)), -1, np.int64)
    dists = np.full((len(queries), max(k, 0)), np.inf)
    # A block of rows at a time: bounded memory even when degenerate signatures make
    # most rows candidates.
    step = max(1, _BLOCK_ELEMS // 8 // max(matrix.shape[1], 1))
    for i, q in enumerate(queries):
        c = cand[i][cand[i] >= 0]
        exact = np.empty(len(c))
        q64 = q.astype(np.float64)
        for a in range(0, len(c), step):
            diff = matrix[c[a : a + step]].astype(np.float64) - q64
            exact[a : a + step] = np.einsum("ij,ij->i", diff, diff)
        order = np.lexsort((c, exact))[: max(k, 0)]
        rows[i, : len(order)], dists[i, : len(order)] = c[order], np.sqrt(exact[order])
    return rows, dists


def _nearest(
    matrix: np.ndarray, q: np.ndarray, cand: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """One query's k nearest candidates (fewer if fewer are given), as `exact_topk`."""
    rows, dists = exact_topk(matrix, q[None], cand[None], min(k, len(cand)))
    return rows[0], dists[0]


class _Int8Codes:
    """The signatures as int8 codes, `x ~ offset + scale * c` per dimension, with each
    row's reconstruction error; the compiled core bounds distances from them."""

    @staticmethod
    def available() -> bool:
        try:
            from disco_cli import _core  # deferred: a core without it falls back to NumPy
        except ImportError:
            return False
        return hasattr(_core, "int8_candidates")

    def __init__(self, matrix: np.ndarray, sq_norms: np.ndarray):
        from disco_cli import _core  # deferred: looked up at each call: tests replace it

        self._core = _core
        # Codes centred on each dimension's midrange span its whole range: a step of
        # (max - min) / 254, never more than the mean's max(max - mean, mean - min) / 127
        # and far less on skewed values (|normal| ones: 0.6 of it, and 0.6 times the
        # candidates on a synthetic 10,000-scan map). Any offset keeps the search exact.
        low = matrix.min(axis=0).astype(np.float64)
        high = matrix.max(axis=0).astype(np.float64)
        self.offset = (low + high) / 2.0
        # A constant dimension gets scale 1 and codes 0: its error is exactly 0.
        self.scale = np.where(high > low, (high - low) / 254.0, 1.0)
        # One pass in the compiled core (double precision), rounded up: the error bound
        # must never be below the true error.
        self.codes, self.code_sq, self.code_norm, err = _core.int8_encode(
            matrix, self.offset, self.scale, get_threads()
        )
        self.err = err * (1 + 1e-9) + 1e-12 * (np.sqrt(sq_norms) + 1.0)

    def candidates(
        self, q: np.ndarray, k: int, lim: int, exclude: np.ndarray | None, threads: int
    ) -> np.ndarray:
        """The rows (< lim, not excluded) that can be among q's k nearest; the core
        rounds q to int16 weights itself (`int8_query` in int8_search.hpp)."""
        ex = None if exclude is None else np.ascontiguousarray(exclude, dtype=np.uint8)
        return self._core.int8_candidates(
            self.codes,
            self.code_sq,
            self.code_norm,
            self.err,
            np.ascontiguousarray(q, dtype=np.float32),
            self.offset,
            self.scale,
            int(k),
            int(lim),
            ex,
            int(threads),
        )


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
# The projections are held in tiles of this many rows (`_core.projected_approx` reads
# one tile, [PROJECTED_DIMS, PROJECTED_TILE], at a time: the whole pass in memory order).
PROJECTED_TILE = 64


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
        # [ceil(N / PROJECTED_TILE), p, PROJECTED_TILE], zeros past the last row.
        tiles = np.zeros((-(-n // PROJECTED_TILE) * PROJECTED_TILE, projected.shape[1]), np.float32)
        tiles[:n] = projected
        self.tiles = np.ascontiguousarray(
            tiles.reshape(-1, PROJECTED_TILE, projected.shape[1]).transpose(0, 2, 1)
        )

    def search(
        self, queries: np.ndarray, k: int, limit: Any = None, exclude: Any = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Approximate top-k rows and exact distances [B, k] (padded with -1, inf)."""
        q = np.atleast_2d(np.asarray(queries, np.float32))
        b, n = len(q), len(self.matrix)
        pq = (q - self.mean) @ self.axes
        approx = self._approx(pq)  # [B, N]: the distance less |pq|^2, per row
        if limit is not None:
            lim = np.broadcast_to(np.asarray(limit, np.int64), (b,))
            approx[np.arange(n)[None] >= lim[:, None]] = np.inf
        if exclude is not None:
            approx[np.broadcast_to(np.asarray(exclude, bool), (b, n))] = np.inf
        wide = min(n, max(k, 0) * PROJECTED_WIDEN)
        if wide == 0:
            return np.full((b, max(k, 0)), -1, np.int64), np.full((b, max(k, 0)), np.inf)
        # Rows past the limit or excluded (infinite here) are not candidates.
        cand = finite_smallest_per_row(approx, wide)  # [B, wide]
        return exact_topk(self.matrix, q, cand, k)

    def _approx(self, pq: np.ndarray) -> np.ndarray:
        """sq - 2 pq . x for every row (float32 [B, N]). The core sums each dot product
        with one fused multiply-add per axis in axis order, as a BLAS sgemm does (NumPy's
        OpenBLAS gives the same bits), from tiles in memory order; without its SIMD
        kernels (a plain level, or no core) NumPy multiplies tile by tile."""
        try:
            from disco_cli import _core  # deferred: a core without it falls back to NumPy

            fast = _core.search_kernel_names()[2] != "plain"
        except (ImportError, AttributeError):
            fast = False
        if fast:
            return _core.projected_approx(self.tiles, self.sq, np.ascontiguousarray(pq))
        dots = np.matmul(pq, self.tiles)  # [T, B, PROJECTED_TILE]
        approx = dots.transpose(1, 0, 2).reshape(len(pq), -1)[:, : len(self.sq)]
        approx *= -2.0
        approx += self.sq
        return approx


# `smallest_per_row` looks at every SAMPLE_STRIDE-th value first: a row's k smallest all
# lie at or below the threshold that SAMPLE_MARGIN times k / stride sampled values reach.
SAMPLE_STRIDE = 16
SAMPLE_MARGIN = 4


def smallest_per_row(values: np.ndarray, k: int) -> np.ndarray:
    """Column indices [B, k] of each row's k smallest values (in no order), as
    `np.argpartition(values, k - 1, axis=1)[:, :k]` finds them (ties aside) in a fifth
    of its time on 10,000 columns: the selection runs on the few values below a
    threshold taken from a strided sample, which holds at least k of them (else the
    whole row is selected from)."""
    b, n = values.shape
    take = SAMPLE_MARGIN * k // SAMPLE_STRIDE + 1
    if n < 4 * SAMPLE_STRIDE * take:
        return np.argpartition(values, k - 1, axis=1)[:, :k]
    sample = values[:, ::SAMPLE_STRIDE]
    limits = np.partition(sample, take - 1, axis=1)[:, take - 1]
    out = np.empty((b, k), np.int64)
    for i in range(b):
        below = np.flatnonzero(values[i] <= limits[i])
        if len(below) < k:  # the sample's values are not a fair picture of the row's
            out[i] = np.argpartition(values[i], k - 1)[:k]
        else:
            out[i] = below[np.argpartition(values[i, below], k - 1)[:k]]
    return out


def finite_smallest_per_row(values: np.ndarray, k: int) -> np.ndarray:
    """Column indices [B, k] of each row's k smallest finite values, -1 in place of
    the non-finite ones (excluded rows). The compiled core picks them as
    `smallest_per_row` does (a strided sample's threshold, then the few values under
    it), ties to the lower column, in (value, column) order
    (`src/cpp/disco/row_selection.hpp`); without the core, `smallest_per_row` does."""
    try:
        from disco_cli import _core  # deferred: looked up at each call: tests replace it

        kernel = _core.smallest_per_row
    except (ImportError, AttributeError):
        cand = smallest_per_row(values, k)
        cand[~np.isfinite(np.take_along_axis(values, cand, axis=1))] = -1
        return cand
    return kernel(np.ascontiguousarray(values, np.float32), int(k))
