"""Exact top-k search over signatures, and matching a query against a map database.

Distances are Euclidean; the result is the same as a plain float64 brute force
(ties broken by row). Two first passes find the rows that can be in the top k, and
those are re-measured directly in float64:

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

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from disco_cli.query_views import candidates_with_views, views_search
from disco_cli.threads import get_threads

__all__ = [
    "SignatureIndex",
    "Match",
    "brute_force_topk",
    "match_queries",
    "check_rerank",
    "rerank_depth",
    "rerank_order",
    "rerank_signature_weight",
    "rerank_wider",
    "check_snap_radius",
    "snap_settings",
    "snap_to_nearest",
    "snap_to_nearest_conf",
]

_EPS32 = float(np.finfo(np.float32).eps)
# Cap on the [rows, queries] float32 distance block, in elements (64 MiB).
_BLOCK_ELEMS = 16 * 1024 * 1024


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
        self, signatures: np.ndarray, int8_min_rows: int = 4096, threads: int | None = None
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
        # None (or 0): disco's thread setting (disco_cli/threads.py), read once.
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
        """`search` for candidates only (a query's side views, `query_views.py`): on a
        map large enough for the int8 pass, the nearest by projected signatures
        (`ProjectedSignatures`) re-measured exactly, which may miss a true neighbour;
        else `search` itself (one matrix product for the whole batch)."""
        if self._codes is None:
            return self.search(queries, k, limit=limit, exclude=exclude)
        if self._projected is None:
            from disco_cli.query_views import ProjectedSignatures

            self._projected = ProjectedSignatures(self.matrix)
        q, _ = checked_queries(queries, self.dim)
        return self._projected.search(q, k, limit=limit, exclude=exclude)

    def _exact(self, q: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """Squared distances in float64, a block of rows at a time (bounded memory even
        when degenerate signatures make most rows candidates)."""
        out = np.empty(len(cand))
        q64 = q.astype(np.float64)
        step = max(1, _BLOCK_ELEMS // 8 // max(self.dim, 1))
        for a in range(0, len(cand), step):
            diff = self.matrix[cand[a : a + step]].astype(np.float64) - q64
            out[a : a + step] = np.einsum("ij,ij->i", diff, diff)
        return out

    def _topk_int8(
        self, q: np.ndarray, lim: int, k: int, exclude: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        assert self._codes is not None
        cand = self._codes.candidates(q, k, lim, exclude, self.threads)
        if len(cand) == 0:
            return np.empty(0, np.int64), np.empty(0)
        if len(cand) > max(4096, lim // 8):
            # Signatures closer together than their int8 error: the bounds prune little,
            # and the float32 product is then cheaper than re-measuring so many rows.
            return self._topk(q, self.matrix[:lim] @ q, lim, k, exclude)
        exact = self._exact(q, cand)
        order = np.lexsort((cand, exact))[:k]
        return cand[order], np.sqrt(exact[order])

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
        cand = np.flatnonzero(approx <= kth + tol)
        exact = self._exact(q, cand)
        order = np.lexsort((cand, exact))[:kk]
        return cand[order], np.sqrt(exact[order])


class _Int8Codes:
    """The signatures as int8 codes, `x ~ mean + scale * c` per dimension, with each
    row's reconstruction error; the compiled core bounds distances from them."""

    @staticmethod
    def available() -> bool:
        try:
            from disco_cli import _core
        except ImportError:
            return False
        return hasattr(_core, "int8_candidates")

    def __init__(self, matrix: np.ndarray, sq_norms: np.ndarray):
        from disco_cli import _core

        self._core = _core
        n, d = matrix.shape
        self.mean = matrix.mean(axis=0, dtype=np.float64)
        spread = np.maximum(matrix.max(axis=0) - self.mean, self.mean - matrix.min(axis=0))
        # A constant dimension gets scale 1 and codes 0: its error is exactly 0.
        self.scale = np.where(spread > 0, spread / 127.0, 1.0)
        # One pass in the compiled core (double precision), rounded up: the error bound
        # must never be below the true error.
        self.codes, self.code_sq, self.code_norm, err = _core.int8_encode(
            matrix, self.mean, self.scale, get_threads()
        )
        self.err = err * (1 + 1e-9) + 1e-12 * (np.sqrt(sq_norms) + 1.0)
        self.g_max = int(_core.int8_query_limit(d))

    def candidates(
        self, q: np.ndarray, k: int, lim: int, exclude: np.ndarray | None, threads: int
    ) -> np.ndarray:
        u = q.astype(np.float64) - self.mean
        w = u * self.scale
        top = float(np.abs(w).max())
        step = top / self.g_max if top > 0 else 1.0
        g = np.clip(np.rint(w / step), -self.g_max, self.g_max).astype(np.int16)
        delta = w - step * g.astype(np.float64)
        delta_norm = float(np.linalg.norm(delta)) * (1 + 1e-9) + 1e-12 * float(np.linalg.norm(w))
        ex = None if exclude is None else np.ascontiguousarray(exclude, dtype=np.uint8)
        return self._core.int8_candidates(
            self.codes,
            self.code_sq,
            self.code_norm,
            self.err,
            g,
            float(u @ u),
            step,
            delta_norm,
            int(k),
            int(lim),
            ex,
            int(threads),
        )


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
    # In [0, 1]: 1 - (the best other heading's correlation peak) / (the yaw's own); low
    # where the place looks alike both ways (model/yaw_refine.py). NaN: the model has none.
    yaw_conf: float = float("nan")


# How many of a query's best matches get the parallax-free yaw (model/yaw_refine.py):
# about 1.5 ms each, so only the best one by default.
REFINE_YAW = 1


def check_rerank(model: Any, rerank: int) -> int:
    """`rerank` when the model can re-rank that many candidates; `DiscoError` otherwise."""
    rerank = int(rerank)
    if rerank < 0:
        from disco_cli.errors import DiscoError

        raise DiscoError(f"rerank must be >= 0, not {rerank}")
    if rerank > 0 and not hasattr(model, "rerank"):
        from disco_cli.errors import DiscoError

        raise DiscoError(f"model {getattr(model, 'name', '?')} cannot re-rank; use --rerank 0")
    return rerank


def check_refine_yaw(n: int) -> int:
    """`n` when it is a valid count of matches to refine the yaw of; `DiscoError` otherwise."""
    n = int(n)
    if n < 0:
        from disco_cli.errors import DiscoError

        raise DiscoError(f"refine_yaw must be >= 0, not {n}")
    return n


def check_snap_radius(model: Any, radius: float) -> float:
    """`radius` (m) when the model can snap its best match to the nearest map scan, or
    it is 0; `DiscoError` otherwise."""
    from disco_cli.errors import DiscoError

    radius = float(radius)
    if not np.isfinite(radius) or radius < 0:
        raise DiscoError(f"snap radius must be a finite distance >= 0 m, not {radius}")
    if radius > 0 and not hasattr(model, "query_position"):
        name = getattr(model, "name", "?")
        raise DiscoError(f"model {name} cannot estimate the query's position; use --snap-radius 0")
    return radius


def refine_yaw_count(model: Any) -> int:
    """How many best matches get the model's parallax-free yaw (0: it has none)."""
    if not hasattr(model, "refine_yaw"):
        return 0
    return check_refine_yaw(getattr(model, "refine_yaw_top", REFINE_YAW))


def rerank_depth(model: Any) -> int:
    """How many nearest signatures the model re-ranks (0: none)."""
    return int(getattr(model, "rerank_candidates", 0) or 0)


def _joined_rows(a: Any, b: Any) -> Any:
    """Two `db.rows` answers (ids, paths, poses, features) as one, a's rows first."""
    return type(a)(
        np.concatenate([a.ids, b.ids]),
        [*a.paths, *b.paths],
        np.concatenate([a.poses, b.poses]),
        np.concatenate([a.features, b.features]),
    )


def _reranked(
    model: Any,
    query_features: np.ndarray,
    db: Any,
    ids: np.ndarray,
    rows: np.ndarray,
    sig_d: np.ndarray,
    first: int,
    wider_above: float,
    views: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, Any, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """The model's re-ranking of the `first` candidates, or of all when none of those
    re-ranks better than `wider_above`: (rows re-ranked, their stored data, re-rank
    distances, yaw, signature distances, the query's own re-rank distances), in one
    order. The yaw is None where the model
    re-ranks by distance alone (`rerank_distances`: its yaw is then worked out for the
    rows kept only).

    The candidates are `rows` (signature distances `sig_d`, nearest first) and, where
    the model makes side views of the query (`views`: what they found, their signature
    distances and their re-rank images), the scans those find among the `first`
    nearest over the query and its views, which join the first pass
    (`query_views.candidates_with_views`); each candidate then re-ranks at its best over
    the query and its views."""
    images = None
    if views is not None:
        view_rows, view_d, images = views
        rows, sig_d, first = candidates_with_views(rows, sig_d, view_rows, view_d, first)

    def reranked(features: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(the query's own re-rank distances, the best over it and its views, yaw)."""
        if images is not None:
            own, best = model.rerank_distances_beside(query_features, features, images)
            return np.asarray(own, np.float64), np.asarray(best, np.float64), None
        if hasattr(model, "rerank_distances"):
            d = np.asarray(model.rerank_distances(query_features, features), np.float64)
            return d, d, None
        d, yaw = model.rerank(query_features, features)
        d = np.asarray(d, np.float64)
        return d, d, np.asarray(yaw, np.float64)

    r = rows[:first]
    stored = db.rows(ids[r])
    own, d, yaw = reranked(stored.features)
    if len(rows) > len(r) and d.min() > wider_above:
        # No candidate is a good match: re-rank the next ones too.
        more = db.rows(ids[rows[len(r) :]])
        own_more, d_more, yaw_more = reranked(more.features)
        r, stored = rows, _joined_rows(stored, more)
        own, d = np.concatenate([own, own_more]), np.concatenate([d, d_more])
        yaw = None if yaw is None else np.concatenate([yaw, yaw_more])
    return r, stored, d, yaw, sig_d[: len(r)], own


def rerank_signature_weight(model: Any) -> float:
    """The weight of the signature distance in the model's re-ranked order (0: the
    re-rank distance alone; `rerank_order`)."""
    return float(getattr(model, "rerank_signature_weight", 0.0) or 0.0)


def rerank_order(
    rows: np.ndarray, rerank_d: np.ndarray, signature_d: np.ndarray, weight: float
) -> np.ndarray:
    """Indices of re-ranked candidates, best first: by `rerank_d - weight / signature_d`,
    ties by row.

    The re-rank distance compares the query's feature images with each candidate
    scan's own. Where the query was taken 4-8 m to the side of every candidate, or the
    street looks alike all along, those distances differ by a few hundredths of noise;
    a near signature (the scan's nearest, side views included) then tells the place
    apart. The bonus `weight / d` grows fast as d shrinks and changes little among far
    signatures: under heavy change, where every signature is far, the re-ranking
    decides, as it does without the signature."""
    score = np.asarray(rerank_d, np.float64)
    if weight:
        # A signature at distance 0 (a copy) wins; the floor keeps the score finite.
        score = score - weight / np.maximum(np.asarray(signature_d, np.float64), 1e-9)
    return np.lexsort((rows, score))


def rerank_wider(model: Any, first: int) -> tuple[int, float]:
    """The model's second re-ranking pass after `first` candidates: (depth, distance), run
    when the best of the first pass re-ranks worse than the distance; (0, inf) for none."""
    depth = int(getattr(model, "rerank_wider", 0) or 0)
    if first <= 0 or depth <= first:
        return 0, float("inf")
    return depth, float(model.rerank_wider_above)


def snap_settings(model: Any) -> tuple[float, float]:
    """(radius m, margin) of the model's snap to the nearest map scan; (0, 0) for none."""
    radius = float(getattr(model, "snap_radius", 0.0) or 0.0)
    if radius <= 0 or not hasattr(model, "query_position"):
        return 0.0, 0.0
    return radius, float(model.snap_margin)


def query_on_map(
    model: Any, query_features: np.ndarray, match_features: np.ndarray, pose: np.ndarray
) -> tuple[float, np.ndarray]:
    """(parallax-free yaw to the match, x, y [2] of the query sensor on the map), from one
    match whose `pose` is its x, y, z, yaw (rad) on the map (`model.query_position`)."""
    yaw, xy, _ = query_on_map_conf(model, query_features, match_features, pose)
    return yaw, xy


def query_on_map_conf(
    model: Any, query_features: np.ndarray, match_features: np.ndarray, pose: np.ndarray
) -> tuple[float, np.ndarray, float]:
    """`query_on_map` and the yaw's confidence (NaN where the model gives none)."""
    if hasattr(model, "query_position_conf"):
        yaw, t, conf = model.query_position_conf(query_features, match_features)
    else:
        (yaw, t), conf = model.query_position(query_features, match_features), float("nan")
    c, s = np.cos(pose[3]), np.sin(pose[3])
    return (
        yaw,
        np.asarray(pose[:2], np.float64) + np.array([c * t[0] - s * t[1], s * t[0] + c * t[1]]),
        float(conf),
    )


def snap_to_nearest(
    model: Any,
    query_features: np.ndarray,
    stored: Any,
    order: np.ndarray,
    distances: np.ndarray,
    radius: float,
    margin: float,
) -> tuple[np.ndarray, float | None]:
    """`order` (indices into `stored` and `distances`, best first) with the map scan
    nearest the query's position first, and the parallax-free yaw of that first one
    (None where the best match has no pose, or the scan snapped to no heading).

    Where the snap moves the first, its yaw is the best match's carried over by the
    two map poses a few metres apart (the query's heading on the map is the best
    match's heading plus the yaw to it), not searched for again.

    The query's position is estimated from the best match alone (its pose on the map
    plus `model.query_position`); the candidates that may take its place lie within
    `radius` m of it on the map and re-rank within `margin` of its distance. Alike
    neighbours of one street re-rank within a few hundredths of each other, so the
    first of the order is often the scan a metre or two past the query's; the pose
    says which is nearer. Without a pose on the best match, `order` stays."""
    order, yaw, _ = snap_to_nearest_conf(
        model, query_features, stored, order, distances, radius, margin
    )
    return order, yaw


def snap_to_nearest_conf(
    model: Any,
    query_features: np.ndarray,
    stored: Any,
    order: np.ndarray,
    distances: np.ndarray,
    radius: float,
    margin: float,
) -> tuple[np.ndarray, float | None, float]:
    """`snap_to_nearest` and the confidence of the yaw it returns (NaN with none)."""
    best = int(order[0])
    pose = np.asarray(stored.poses, dtype=np.float64)
    if not np.isfinite(pose[best, [0, 1, 3]]).all():
        return order, None, float("nan")
    yaw, estimate, conf = query_on_map_conf(
        model, query_features, stored.features[best], pose[best]
    )
    xy = pose[order, :2]
    with np.errstate(invalid="ignore"):  # NaN poses compare False: never candidates
        near = np.hypot(*(xy - pose[best, :2]).T) <= radius
    alike = distances[order] <= distances[best] + margin
    cands = order[near & alike]  # holds best itself
    nearest = int(cands[np.argmin(np.hypot(*(pose[cands, :2] - estimate).T))])
    if nearest == best:
        return order, yaw, conf
    moved = np.r_[nearest, order[order != nearest]]
    if not np.isfinite(pose[nearest, 3]):
        return moved, None, float("nan")
    # The query's heading on the map is the best match's plus the yaw to it; the yaw to
    # the scan snapped to follows from the two map poses, a few metres apart.
    turned = yaw + math.degrees(pose[best, 3] - pose[nearest, 3])
    return moved, float(_wrapped_deg(turned)), conf


def _wrapped_deg(yaw: float) -> float:
    """An angle in degrees in (-180, 180]."""
    out = (yaw + 180.0) % 360.0 - 180.0
    return 180.0 if out <= -180.0 else out


def _yaw_conf(
    model: Any, query_features: np.ndarray, match_features: np.ndarray, refined: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The model's yaw [K] of the matches, parallax-free (`refine_yaw`) or from one phase
    correlation (`yaw`), and its confidence [K] (NaN where the model gives none)."""
    name = "refine_yaw" if refined else "yaw"
    if hasattr(model, f"{name}_conf"):
        yaw, conf = getattr(model, f"{name}_conf")(query_features, match_features)
        return np.asarray(yaw, np.float64), np.asarray(conf, np.float64)
    yaw = np.asarray(getattr(model, name)(query_features, match_features), np.float64)
    return yaw, np.full(len(yaw), np.nan)


def _coarse_conf(
    model: Any,
    query_features: np.ndarray,
    match_features: np.ndarray,
    yaw: np.ndarray,
    conf: np.ndarray,
) -> None:
    """Fills the confidence of the rows whose yaw was not refined (NaN in `conf`) from the
    model's phase correlation, where the model gives one and it gave the yaw."""
    todo = np.flatnonzero(np.isnan(conf))
    if len(todo) == 0 or not hasattr(model, "yaw_conf"):
        return
    coarse, c = model.yaw_conf(query_features, match_features[todo])
    # Only where the row's yaw is that phase correlation's (not another re-ranker's).
    same = np.abs((np.asarray(coarse, np.float64) - yaw[todo] + 180.0) % 360.0 - 180.0) < 1e-3
    conf[todo[same]] = np.asarray(c, np.float64)[same]


def makes_query_views(model: Any) -> bool:
    """Whether the model makes side views of a query (`DiscoModel.query_views`)."""
    return hasattr(model, "query_views") and len(getattr(model, "query_view_offsets", ())) > 0


def _views_found(
    model: Any,
    index: Any,
    query_features: np.ndarray,
    k: int,
    limit: Any,
    exclude: Any,
    i: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What query i's side views find: (rows [V, k], signature distances [V, k],
    re-rank images [V, R, S]), within the query's `limit`/`exclude`."""
    sigs, images = model.query_views(query_features)
    lim = limit if np.ndim(limit) == 0 else int(np.asarray(limit)[i])  # None: ndim 0
    ex = None
    if exclude is not None:
        ex = np.asarray(exclude, dtype=bool)
        ex = ex[i] if ex.ndim == 2 else ex
    view_rows, view_d = views_search(index, sigs, k, limit=lim, exclude=ex)
    return view_rows, view_d, images


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
    rerank: int | None = None,
    refine_yaw: int | None = None,
    snap_radius: float | None = None,
) -> list[list[Match]]:
    """Top-k matches of each query with their yaw: signature search, then the model's
    `rerank` hook when it asks for one (DiSCO, Scan Context), then yaw from the stored
    features of the top rows only. `db` is a `Database` (anything with `rows(ids)`).
    `rerank` overrides the model's re-ranking depth; where the best of those re-ranks
    worse than the model's `rerank_wider_above`, the candidates down to its
    `rerank_wider` are re-ranked too (`rerank_wider`). The re-ranked candidates are
    ordered by their re-rank distance less the model's `rerank_signature_weight` over
    their signature distance (`rerank_order`); `Match.distance` stays the re-rank
    distance. Where the map has poses, the re-ranked best is then snapped to the map
    scan nearest the query (`snap_to_nearest`, within `snap_radius` m, default the
    model's `snap_radius`; 0: never). The yaw of the best `refine_yaw` matches (default:
    the model's `refine_yaw_top`, else `REFINE_YAW`) is re-estimated without parallax
    when the model can (its `refine_yaw` hook)."""
    if refine_yaw is None:
        refine_n = refine_yaw_count(model)
    else:
        refine_n = check_refine_yaw(refine_yaw) if hasattr(model, "refine_yaw") else 0
    rerank_n = rerank_depth(model) if rerank is None else check_rerank(model, rerank)
    first = max(k, rerank_n) if rerank_n > 0 else k
    wider_n, wider_above = rerank_wider(model, first) if rerank_n > 0 else (0, float("inf"))
    sig_weight = rerank_signature_weight(model)
    snap_r, snap_margin = snap_settings(model)
    if snap_radius is not None:
        snap_r = check_snap_radius(model, snap_radius)
        snap_margin = float(getattr(model, "snap_margin", 0.0))
    if rerank_n == 0:  # the signature order has no re-ranked candidates to snap among
        snap_r = 0.0
    rows, dists = index.search(signatures, max(first, wider_n), limit=limit, exclude=exclude)
    with_views = (
        rerank_n > 0 and makes_query_views(model) and hasattr(model, "rerank_distances_beside")
    )
    out: list[list[Match]] = []
    for i in range(len(rows)):
        keep = rows[i] >= 0
        r_all, d_all = rows[i][keep], dists[i][keep]
        if len(r_all) == 0:
            out.append([])
            continue
        first_yaw, first_conf = None, float("nan")
        if rerank_n > 0:
            views = None
            if with_views:
                views = _views_found(model, index, features[i], first, limit, exclude, i)
            r, stored, d_new, yaw, sig_d, d_own = _reranked(
                model, features[i], db, ids, r_all, d_all, first, wider_above, views
            )
            order = rerank_order(r, d_new, sig_d, sig_weight)
            if snap_r > 0:
                # The margin compares how well the query itself matches each candidate:
                # a view's match may stand far ahead of a nearer scan it cannot see.
                order, first_yaw, first_conf = snap_to_nearest_conf(
                    model, features[i], stored, order, d_own, snap_r, snap_margin
                )
            order = order[:k]
            # Shown: how well the query itself matches (a view's match orders, and is
            # not as sure as that).
            r, d = r[order], d_own[order]
            yaw = None if yaw is None else yaw[order]
            sel = order
        else:  # the search returned `first` rows: no wider pass without re-ranking
            r, d = r_all, d_all
            stored = db.rows(ids[r])
            sel = np.arange(len(r))
            yaw = None
        if max_distance is not None:
            ok = d <= max_distance
            r, d, sel = r[ok], d[ok], sel[ok]
            if yaw is not None:
                yaw = yaw[ok]
        conf = np.full(len(r), np.nan)
        if len(r) and yaw is None:
            yaw, conf = _yaw_conf(model, features[i], stored.features[sel], refined=False)
        if len(r) and refine_n > 0:
            todo = np.arange(min(refine_n, len(r)))
            if first_yaw is not None and sel[0] == order[0]:  # the snap refined it
                yaw[0], conf[0], todo = first_yaw, first_conf, todo[1:]
            if len(todo):
                yaw[todo], conf[todo] = _yaw_conf(
                    model, features[i], stored.features[sel[todo]], refined=True
                )
        if len(r):
            _coarse_conf(model, features[i], stored.features[sel], yaw, conf)
        out.append(
            [
                Match(
                    rank=j + 1,
                    row=int(r[j]),
                    match_id=int(stored.ids[sel[j]]),
                    path=stored.paths[sel[j]],
                    distance=float(d[j]),
                    yaw_deg=float(yaw[j]),
                    pose=stored.poses[sel[j]],
                    yaw_conf=float(conf[j]),
                )
                for j in range(len(r))
            ]
        )
    return out
