"""`MilvusIndex`: a Milvus map's signature search, with `SignatureIndex.search`'s contract."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from disco_cli.maps.milvus_address import milvus_errors as _milvus_errors

__all__ = ["MilvusIndex"]

# Extra candidates a search fetches beyond k, re-measured exactly here: Milvus's float32
# distances may order near-ties at the k-th place otherwise than the exact search.
_MARGIN = 16
# Milvus's largest top-k.
_TOPK_MAX = 16384


class MilvusIndex:
    """`SignatureIndex.search`'s contract over a Milvus collection, for the scans `ids`
    (the snapshot: a scan appended since is not answered). Milvus proposes the nearest
    k + a margin; their distances are measured again here in float64, so the order is
    the exact search's (ties by row)."""

    def __init__(self, db: Any, ids: np.ndarray):
        self._db = db
        self._ids = np.asarray(ids, np.int64)
        self._matrix: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def dim(self) -> int:
        return self._db.signature_dim

    @property
    def matrix(self) -> np.ndarray:
        """Every snapshot scan's signature (read from Milvus once; `Map.stored`)."""
        if self._matrix is None:
            ids, sigs = self._db.signatures()
            at = {int(i): k for k, i in enumerate(ids)}
            self._matrix = np.zeros((len(self._ids), self.dim), np.float32)
            for r, i in enumerate(self._ids):
                if int(i) in at:
                    self._matrix[r] = sigs[at[int(i)]]
        return self._matrix

    @_milvus_errors
    def _milvus_search(self, q: np.ndarray, k: int, filt: str) -> list:
        db = self._db
        params: dict[str, Any] = {"metric_type": "L2"}
        if db.meta.get("index_type") == "HNSW":
            params["params"] = {"ef": max(64, 2 * k)}
        return db._client.search(
            db._scans,
            data=[q.tolist()],
            limit=k,
            filter=filt,
            output_fields=["sig"],
            search_params=params,
            consistency_level="Strong",
        )[0]

    @property
    def path(self) -> Any:  # for _milvus_errors' message
        return self._db.path

    def search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(queries, dtype=np.float32)
        single = q.ndim == 1
        q = q.reshape(1, -1) if single else q
        if q.ndim != 2 or q.shape[1] != self.dim or not np.isfinite(q).all():
            raise ValueError(f"queries must be finite [B, {self.dim}], got {q.shape}")
        b, n = len(q), len(self._ids)
        lims = (
            np.full(b, n) if limit is None else np.broadcast_to(np.asarray(limit, np.int64), (b,))
        )
        if exclude is not None:
            exclude = np.asarray(exclude, dtype=bool)
            if exclude.ndim == 1:
                exclude = np.broadcast_to(exclude, (b, n))
        rows = np.full((b, k), -1, np.int64)
        dists = np.full((b, k), np.inf)
        for i in range(b):
            lim = int(min(max(lims[i], 0), n))
            if k <= 0 or lim == 0:
                continue
            ex = np.zeros(lim, bool) if exclude is None else np.asarray(exclude[i, :lim])
            left_out = self._ids[:lim][ex]
            filt = f"id <= {int(self._ids[lim - 1])}"
            if 0 < len(left_out) <= 1000:
                filt += f" and id not in {left_out.tolist()}"
            want = min(k + _MARGIN + (len(left_out) if len(left_out) > 1000 else 0), _TOPK_MAX)
            hits = self._milvus_search(q[i], want, filt)
            hid = np.array([int(h["id"]) for h in hits], np.int64)
            vec = np.array([h["entity"]["sig"] for h in hits], np.float64).reshape(-1, self.dim)
            r = np.searchsorted(self._ids, hid)
            ok = (r < lim) & (self._ids[np.minimum(r, n - 1)] == hid)
            r, vec = r[ok], vec[ok]
            keep = ~ex[r]
            r, vec = r[keep], vec[keep]
            d = np.sqrt(((vec - q[i].astype(np.float64)) ** 2).sum(axis=1))
            order = np.lexsort((r, d))[:k]
            rows[i, : len(order)] = r[order]
            dists[i, : len(order)] = d[order]
        return (rows[0], dists[0]) if single else (rows, dists)

    approximate_search = search
