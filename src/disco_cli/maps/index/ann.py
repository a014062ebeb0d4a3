"""The approximate signature index for big maps (faiss; `pip install 'disco-cli[ann]'`).

Layout (chosen by measurement at 1,000,000 signatures, docs/benchmarks.md#a-million-scans):

1. a PCA to 256 dimensions (96 % of the signatures' variance), from 8,192 rows on;
2. an inverted file of `nlist` clusters (about sqrt(N)) holding each row's 8-bit
   code (one byte per dimension); a query scans the `nprobe` nearest clusters;
3. the `k_factor * k` best of those re-measured with 8-bit codes of all 1024
   dimensions (faiss `IndexRefine`), of which the k best are returned.

That is about 1,300 bytes per scan (1.3 GB at a million) against 4 KiB for the exact
index's float32 matrix. Distances are those of the 8-bit codes (within a few 1e-3 of
the exact ones). With `nprobe = nlist`, a `k_factor` that covers the map and
`refine="Flat"` (float32, 4 KiB per scan), every row is a candidate and the result is the
exact top k.

The index lives in a sidecar beside the map (`map.db.ann`): faiss's own serialization,
then the map's scan ids, then a JSON header (the map's key from `index.map_key`, the
parameters and a SHA-256 of everything before it), its length and a magic. It is
written to a temporary name and renamed into place, and read only after its checksum
holds: a damaged or stale sidecar is rebuilt, never trusted.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io.output_paths import atomic_path
from disco_cli.maps.index import INSTALL_HINT, map_key, sidecar_path
from disco_cli.maps.map_side_views import ViewIndex
from disco_cli.maps.signature_index import checked_queries

__all__ = ["AnnParams", "AnnIndex", "default_params", "open_or_build", "SidecarError"]

_MAGIC = b"DISCOANN"
_TRAILER = struct.Struct("<Q8s")  # header length, magic
_FORMAT = 1
_PCA_DIM = 256
_PCA_MIN_ROWS = 8192
_REFINE = ("SQ8", "SQfp16", "Flat")
# A query's side views search half the clusters, re-measuring twice k: they only
# propose candidates, which are re-ranked (`approximate_search`).
VIEW_PROBE_DIVISOR = 2
VIEW_K_FACTOR = 2.0


class SidecarError(Exception):
    """A sidecar that cannot be used (missing, damaged, another format or map)."""


@dataclass(frozen=True)
class AnnParams:
    nlist: int  # inverted-file clusters
    nprobe: int  # clusters scanned per query
    pca: int  # dimensions after the PCA (0: none)
    k_factor: int  # candidates re-measured in full dimension, per result
    refine: str = "SQ8"  # codes they are re-measured with: SQ8, SQfp16 or Flat (float32)

    def check(self) -> AnnParams:
        if min(self.nlist, self.nprobe, self.k_factor) < 1 or self.pca < 0:
            raise ValueError(f"approximate index: bad parameters {self}")
        if self.refine not in _REFINE:
            raise ValueError(f"approximate index: refine is one of {', '.join(_REFINE)}")
        return self


def default_params(n: int, dim: int) -> AnnParams:
    """The parameters for a map of `n` signatures of `dim` dimensions: about sqrt(n)
    clusters (a power of two, at least 39 training rows each, as faiss's k-means
    asks), an eighth of them scanned but at least 4,096 rows' worth (every row of a
    small map: scanning them costs microseconds), 10 candidates re-measured per result.

    A query's time goes to the codes of the clusters it scans (n / 8 of them), not to
    finding the clusters, so more clusters would not make it faster at the same share
    scanned; they would make the build slower (its clustering grows as nlist^2). At a
    million scans an eighth took 2.3 ms per query and found the exact top 1 for 96 %
    of the queries (a sixteenth: 1.0 ms, 94 %; docs/benchmarks.md)."""
    nlist = 2 ** round(math.log2(max(math.sqrt(max(n, 1)), 1.0)))
    nlist = int(max(1, min(nlist, n // 39, 65536)))
    pca = _PCA_DIM if dim > _PCA_DIM and n >= _PCA_MIN_ROWS else 0
    nprobe = max(nlist // 8, math.ceil(nlist * 4096 / max(n, 1)))
    return AnnParams(nlist=nlist, nprobe=min(max(nprobe, 1), nlist), pca=pca, k_factor=10)


def _faiss() -> Any:
    try:
        import faiss  # deferred: optional extra
    except ImportError:
        raise DiscoError(INSTALL_HINT) from None
    return faiss


class AnnIndex:
    """Approximate top-k search over `[N, D]` signatures (`SignatureIndex.search`'s
    contract without `limit`)."""

    def __init__(self, index: Any, n: int, dim: int, params: AnnParams):
        self._index = index
        self.n = n
        self._dim = dim
        self.params = params
        self.set_search(params.nprobe, params.k_factor)

    @classmethod
    def build(
        cls, signatures: np.ndarray, params: AnnParams | None = None, seed: int = 1234
    ) -> AnnIndex:
        faiss = _faiss()
        x = np.ascontiguousarray(signatures, dtype=np.float32)
        if x.ndim != 2 or len(x) == 0:
            raise ValueError(f"signatures must be a non-empty [N, D], got {x.shape}")
        n, dim = x.shape
        p = (params or default_params(n, dim)).check()
        coarse = f"IVF{p.nlist},SQ8"
        if p.pca:
            coarse = f"PCA{p.pca},{coarse}"
        base = faiss.index_factory(dim, coarse, faiss.METRIC_L2)
        # A small map trains fewer than faiss's 39 rows per cluster: fine, and not worth
        # its warning on stderr.
        faiss.extract_index_ivf(base).cp.min_points_per_centroid = 1
        index = faiss.IndexRefine(base, faiss.index_factory(dim, p.refine, faiss.METRIC_L2))
        # k-means and the PCA learn from a sample: 64 rows per cluster is plenty.
        rng = np.random.default_rng(seed)
        take = min(n, max(64 * p.nlist, 4 * p.pca, 1000))
        sample = x if take == n else x[np.sort(rng.choice(n, take, replace=False))]
        index.train(sample)
        for s in range(0, n, 65536):  # bounded temporary memory
            index.add(x[s : s + 65536])
        return cls(index, n, dim, p)

    def set_search(self, nprobe: int, k_factor: int) -> None:
        """How hard a search looks: clusters scanned and candidates re-measured per
        result (`nprobe = nlist` with a `k_factor` that covers the map: every row)."""
        faiss = _faiss()
        faiss.extract_index_ivf(self._index).nprobe = int(min(max(nprobe, 1), self.params.nlist))
        self._index.k_factor = float(max(k_factor, 1))

    def __len__(self) -> int:
        return self.n

    @property
    def dim(self) -> int:
        return self._dim

    def memory_bytes(self) -> int:
        """What the codes and lists hold (faiss's own serialized size)."""
        return int(_faiss().serialize_index(self._index).nbytes)

    def search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        return self._search(queries, k, limit, exclude, None)

    def approximate_search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """`search` for candidates only (a query's side views, `query_views.py`): half
        the clusters probed and twice k re-measured, so that a query's four views cost
        about what two of its own searches do."""
        faiss = _faiss()
        nprobe = max(1, faiss.extract_index_ivf(self._index).nprobe // VIEW_PROBE_DIVISOR)
        params = faiss.IndexRefineSearchParameters(
            k_factor=VIEW_K_FACTOR,
            base_index_params=self._ivf_params(faiss, nprobe),
        )
        return self._search(queries, k, limit, exclude, params)

    def _ivf_params(self, faiss: Any, nprobe: int) -> Any:
        """Per-call IVF search parameters, wrapped for the PCA in front where there is one."""
        ivf = faiss.SearchParametersIVF(nprobe=nprobe)
        if self.params.pca:
            return faiss.SearchParametersPreTransform(index_params=ivf)
        return ivf

    def _search(
        self,
        queries: np.ndarray,
        k: int,
        limit: Sequence[int] | np.ndarray | None,
        exclude: np.ndarray | None,
        params: Any,
    ) -> tuple[np.ndarray, np.ndarray]:
        if limit is not None:
            raise ValueError("the approximate index searches a whole map (no limit)")
        q, single = checked_queries(queries, self._dim)
        b, k = len(q), max(int(k), 0)
        rows = np.full((b, k), -1, dtype=np.int64)
        dists = np.full((b, k), np.inf)
        if k == 0:
            return (rows[0], dists[0]) if single else (rows, dists)
        if exclude is not None:
            exclude = np.broadcast_to(np.asarray(exclude, dtype=bool), (b, self.n))
        # Excluded rows are dropped after the search: fetching k more than there are
        # excluded rows still leaves the k best allowed ones.
        extra = 0 if exclude is None else int(exclude.sum(axis=1).max())
        fetch = min(k + extra, self.n)
        d2, found = self._index.search(q, fetch, params=params)
        for i in range(b):
            ok = found[i] >= 0
            if exclude is not None:
                ok &= ~exclude[i, np.maximum(found[i], 0)]
            r, d = found[i][ok][:k], d2[i][ok][:k]
            rows[i, : len(r)] = r
            dists[i, : len(d)] = np.sqrt(np.maximum(d, 0.0))
        return (rows[0], dists[0]) if single else (rows, dists)

    # -- the sidecar ----------------------------------------------------------------

    def save(self, path: Path, key: dict, ids: np.ndarray, owner: np.ndarray | None) -> None:
        """Write the sidecar at `path` atomically (a temporary file renamed into place)."""
        faiss = _faiss()
        path = Path(path)
        with atomic_path(path) as tmp:
            faiss.write_index(self._index, str(tmp))
            index_bytes = tmp.stat().st_size
            ids = np.ascontiguousarray(ids, dtype="<i8")
            own = np.ascontiguousarray(
                np.empty(0, np.int64) if owner is None else owner, dtype="<i8"
            )
            with open(tmp, "ab") as fh:
                fh.write(ids.tobytes())
                fh.write(own.tobytes())
            header = {
                "format": _FORMAT,
                "key": key,
                "params": asdict(self.params),
                "rows": self.n,
                "dim": self._dim,
                "index_bytes": index_bytes,
                "ids": len(ids),
                "owner": len(own),
                "sha256": _sha256(tmp, tmp.stat().st_size),
            }
            blob = json.dumps(header, sort_keys=True).encode()
            with open(tmp, "ab") as fh:
                fh.write(blob)
                fh.write(_TRAILER.pack(len(blob), _MAGIC))
                fh.flush()
                os.fsync(fh.fileno())

    @classmethod
    def load(cls, path: Path, key: dict) -> tuple[AnnIndex, np.ndarray, np.ndarray | None]:
        """`(index, ids, owner rows or None)` from the sidecar `path`; `SidecarError`
        naming why when it is missing, damaged or of another state of the map."""
        faiss = _faiss()
        path = Path(path)
        try:
            size = path.stat().st_size
            with open(path, "rb") as fh:
                if size < _TRAILER.size:
                    raise SidecarError("truncated")
                fh.seek(size - _TRAILER.size)
                hlen, magic = _TRAILER.unpack(fh.read(_TRAILER.size))
                if magic != _MAGIC or hlen > size - _TRAILER.size:
                    raise SidecarError("not an index file of disco's, or truncated")
                body = size - _TRAILER.size - hlen
                fh.seek(body)
                header = json.loads(fh.read(hlen))
                if header.get("format") != _FORMAT:
                    raise SidecarError(f"index format {header.get('format')!r}")
                if header.get("key") != key:
                    raise SidecarError("the map changed since it was built")
                n, dim = int(header["rows"]), int(header["dim"])
                ib, n_ids, n_own = (int(header[f]) for f in ("index_bytes", "ids", "owner"))
                if ib + 8 * (n_ids + n_own) != body:
                    raise SidecarError("sizes do not add up")
                if _sha256(path, body) != header["sha256"]:
                    raise SidecarError("checksum mismatch (damaged)")
                fh.seek(ib)
                ids = np.frombuffer(fh.read(8 * n_ids), dtype="<i8").astype(np.int64)
                own = np.frombuffer(fh.read(8 * n_own), dtype="<i8").astype(np.int64)
            params = AnnParams(**header["params"]).check()
        except SidecarError:
            raise
        except FileNotFoundError:
            raise SidecarError("missing") from None
        except (OSError, ValueError, KeyError, TypeError, struct.error) as exc:
            raise SidecarError(f"unreadable ({exc})") from None
        # The checksum held, so this is the index that was written (by this faiss or
        # another version, which may not read it).
        try:
            index = faiss.read_index(str(path))
        except RuntimeError as exc:
            raise SidecarError(f"faiss cannot read it ({str(exc).splitlines()[0]})") from None
        if index.ntotal != n or index.d != dim:
            raise SidecarError("the index does not hold its rows")
        return cls(index, n, dim, params), ids, (own if n_own else None)


def _sha256(path: Path, nbytes: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        left = nbytes
        while left > 0:
            chunk = fh.read(min(left, 1 << 22))
            if not chunk:
                raise SidecarError("truncated")
            h.update(chunk)
            left -= len(chunk)
    return h.hexdigest()


def open_or_build(
    db: Any, note: Any = None, params: AnnParams | None = None
) -> tuple[np.ndarray, Any]:
    """`(ids, index)` of the map `db` from its sidecar when that is current; else built
    from the map's signatures (and side views) and saved beside it for the next time."""
    say = note or (lambda _msg: None)
    path = sidecar_path(db.path)
    key = map_key(db)
    try:
        index, ids, owner = AnnIndex.load(path, key)
        if params is not None and index.params != params.check():
            raise SidecarError("built with other parameters")
        if owner is None:
            return ids, index
        return ids, ViewIndex.over(index, len(ids), owner)
    except SidecarError as exc:
        if path.exists():
            say(f"{path}: {exc}; rebuilding the approximate index")
        else:
            say(f"{path}: building the approximate index of {key['rows']} scans")
    ids, sigs = db.signatures()
    owner = None
    if db.side_offsets:
        owner_ids, view_sigs = db.side_signatures()
        rows = np.searchsorted(ids, owner_ids)
        known = (rows < len(ids)) & (ids[np.minimum(rows, len(ids) - 1)] == owner_ids)
        owner = rows[known]
        sigs = np.concatenate([sigs, view_sigs[known]])
    index = AnnIndex.build(sigs, params)
    del sigs
    try:
        index.save(path, key, ids, owner)
    except OSError as exc:
        say(f"{path}: cannot save the approximate index ({exc.strerror or exc}); using it unsaved")
    if owner is None:
        return ids, index
    return ids, ViewIndex.over(index, len(ids), owner)
