"""Scan Context (Kim and Kim, IROS 2018) as a disco model: `--model scancontext`.

Written from the paper's description. The descriptor is the 20 x 60 polar max-height
image (rings x sectors, 80 m): each cell holds the height of its highest point above
`z_min` (0 when empty), which is `polar_bev` in `max_height` mode. Search has two steps:

1. the ring key, one number per ring, is rotation-invariant and serves as the
   signature: the database returns the `rerank_candidates` nearest ring keys
   (Euclidean). The paper's ring key is each ring's occupancy (the fraction of
   non-empty cells); ours is by default each ring's mean cell height, because with the
   ground inside the height window nearly every cell is occupied and occupancy stops
   telling places apart: on the held-out simulated towns of docs/results.md the true
   place was among the 10 nearest occupancy keys for 70-90 % of the queries, among
   the 10 nearest mean keys for 98-100 %. `ring_key="occupancy"` gives the paper's;
2. `rerank` compares the full descriptors with the column-shift cosine distance

       d(Q, C) = min over n of  mean over columns j of  1 - cos(Q[:, j], C[:, j - n])

   where the mean runs over the columns that are non-empty in both (1 when none is).
   The best shift n is the rotation: a query that is the candidate rotated by +a
   degrees has Q = roll(C, a / 6 sectors), so n = a / 6 and yaw_deg = -6 n, the yaw
   of T_match<-query (docs/architecture.md). A parabola through the distances at
   n - 1, n, n + 1 refines the yaw below one sector.

No torch here: the whole model is NumPy.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from typing import Any

import numpy as np

from disco_cli.model.bev import BEVConfig
from disco_cli.model.interface import Abilities, Unable
from disco_cli.query.query_policy import NO_RERANKING

RINGS = 20
SECTORS = 60
MAX_RANGE = 80.0
# The paper lifts the points by the sensor's mounting height (about 2 m on a car) so that
# the ground has heights near 0 and every height is positive; z_min plays that part.
Z_MIN = -2.0
Z_MAX = 38.0
CANDIDATES = 10
RING_KEYS = ("mean", "occupancy")


def _default_bev_config() -> Any:
    return BEVConfig(
        rings=RINGS,
        sectors=SECTORS,
        heights=1,
        max_range=MAX_RANGE,
        min_range=0.0,
        z_min=Z_MIN,
        z_max=Z_MAX,
        mode="max_height",
    )


def ring_keys(descriptors: np.ndarray, kind: str = "mean") -> np.ndarray:
    """[B, R] float32 ring keys of [B, R, S] descriptors: each ring's mean cell height
    (`mean`) or its fraction of non-empty cells (`occupancy`, the paper's)."""
    d = np.asarray(descriptors, dtype=np.float64)
    if kind == "mean":
        return d.mean(axis=-1).astype(np.float32)
    if kind == "occupancy":
        return (d > 0).mean(axis=-1).astype(np.float32)
    raise ValueError(f"unknown ring key {kind!r} (known: {', '.join(RING_KEYS)})")


def _unit_columns(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit length (empty ones stay 0) and the mask of non-empty columns."""
    norms = np.linalg.norm(d, axis=-2, keepdims=True)
    valid = norms > 0
    unit = np.divide(d, norms, out=np.zeros_like(d), where=valid)
    return unit, valid[..., 0, :].astype(np.float64)


def shift_distances(query: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """[K, S] distances of the query to each candidate rolled by n = 0..S-1 sectors.

    Entry n compares query column j with candidate column j - n. Computed for all
    shifts at once as a circular cross-correlation (FFT along the sectors).
    """
    q = np.asarray(query, dtype=np.float64)
    c = np.asarray(candidates, dtype=np.float64)
    if q.ndim != 2 or c.ndim != 3 or c.shape[1:] != q.shape:
        raise ValueError(f"query [R, S] and candidates [K, R, S] disagree: {q.shape}, {c.shape}")
    sectors = q.shape[1]
    qu, qv = _unit_columns(q)
    cu, cv = _unit_columns(c)
    # sum_j x[j] y[j - n] has the spectrum X * conj(Y).
    cos_sum = np.fft.irfft(
        (np.fft.rfft(qu, axis=-1)[None] * np.conj(np.fft.rfft(cu, axis=-1))).sum(axis=1), n=sectors
    )
    both = np.fft.irfft(np.fft.rfft(qv)[None] * np.conj(np.fft.rfft(cv, axis=-1)), n=sectors)
    both = np.rint(both)
    return np.where(both > 0, 1.0 - cos_sum / np.maximum(both, 1.0), 1.0)


def best_shift(distances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(minimum distance [K], sub-sector shift [K]) from the [K, S] shift distances."""
    d = np.asarray(distances, dtype=np.float64)
    k = np.arange(len(d))
    n = np.argmin(d, axis=1)
    sectors = d.shape[1]
    left, mid, right = d[k, (n - 1) % sectors], d[k, n], d[k, (n + 1) % sectors]
    curvature = left - 2.0 * mid + right
    # Vertex of the parabola through the three points; flat curves keep the integer shift.
    offset = np.divide(
        0.5 * (left - right), curvature, out=np.zeros_like(mid), where=curvature > 1e-12
    )
    return mid, n + np.clip(offset, -0.5, 0.5)


def _shift_to_yaw(shift: np.ndarray, sectors: int) -> np.ndarray:
    yaw = -np.asarray(shift, np.float64) * (360.0 / sectors)
    wrapped = np.mod(yaw + 180.0, 360.0) - 180.0
    return np.where(wrapped == -180.0, 180.0, wrapped)


class ScanContextModel(Unable):
    """The Scan Context baseline behind `model.interface.QueryModel`: ring-key search,
    then the column-shift distance re-ranks (no wider pass, snap or views)."""

    abilities = Abilities(rerank=True)

    def __init__(
        self, bev_config: Any = None, rerank_candidates: int = CANDIDATES, ring_key: str = "mean"
    ):
        self.name = "scancontext"
        self.bev_config = bev_config if bev_config is not None else _default_bev_config()
        if self.bev_config.mode != "max_height" or self.bev_config.heights != 1:
            raise ValueError("Scan Context needs a single-layer max_height BEV")
        if ring_key not in RING_KEYS:
            raise ValueError(f"unknown ring key {ring_key!r} (known: {', '.join(RING_KEYS)})")
        self.rerank_candidates = int(rerank_candidates)
        self.query_policy = replace(NO_RERANKING, rerank_candidates=self.rerank_candidates)
        self.ring_key = ring_key
        blob = json.dumps(self.config_dict(), sort_keys=True).encode()
        self.fingerprint = hashlib.sha256(blob).hexdigest()[:16]

    def config_dict(self) -> dict[str, Any]:
        return {
            "model": self.name,
            "kind": "scancontext",
            "rerank_candidates": self.rerank_candidates,
            "ring_key": self.ring_key,
            "bev_config": self.bev_config.to_dict(),
        }

    def embed(self, bevs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ring keys [B, R], descriptors [B, R, S]) of max-height BEVs [B, 1, R, S]."""
        b = np.asarray(bevs, dtype=np.float32)
        want = (1, self.bev_config.rings, self.bev_config.sectors)
        if b.ndim != 4 or b.shape[1:] != want:
            raise ValueError(f"bevs must be [B, {want[0]}, {want[1]}, {want[2]}], got {b.shape}")
        features = np.ascontiguousarray(b[:, 0])
        return ring_keys(features, self.ring_key), features

    def rerank(
        self, query_features: np.ndarray, candidate_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(column-shift cosine distances [K] in [0, 2], yaw_deg [K]) of the candidates."""
        candidates = np.asarray(candidate_features)
        if candidates.shape[0] == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.float64)
        dist, shift = best_shift(shift_distances(query_features, candidates))
        return dist.astype(np.float32), _shift_to_yaw(shift, candidates.shape[-1])

    def rerank_distances(
        self, query_features: np.ndarray, candidate_features: np.ndarray
    ) -> np.ndarray:
        """`rerank`'s distances alone."""
        return self.rerank(query_features, candidate_features)[0]

    def yaw(self, query_features: np.ndarray, match_features: np.ndarray) -> np.ndarray:
        """[K] degrees in (-180, 180]: the yaw of T_match<-query for each match."""
        return self.rerank(query_features, match_features)[1]

    def yaw_conf(
        self, query_features: np.ndarray, match_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(`yaw`, NaN: the column shift gives no confidence)."""
        yaw = self.yaw(query_features, match_features)
        return yaw, np.full(len(yaw), np.nan)
