"""Re-ranking the nearest signatures by the aligned cross-correlation of feature images.

The signature is a low-pass |FFT2|: it keeps no phase, so two scans a metre or two apart
along one street can have nearly equal signatures, and the nearest signature is then often
a neighbour of the right scan rather than the right scan itself. The feature images still
hold where things are. Aligned by their best circular shift along sectors (the rotation),
their normalized cross-correlation is a finer measure of how far apart two scans are, and
comparing the top few candidates this way costs a fraction of a millisecond.

The scores come from the compiled core (`_core.aligned_correlations`,
src/cpp/disco/sector_correlation.*) where it has them; the NumPy code below is the
reference the tests compare it with (`BACKEND = "numpy"`) and the fallback.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from disco_cli.model import fft
from disco_cli.model.compiled import compiled_core

# Which code computes the scores: None, the compiled kernel where the core has it, else
# NumPy; "numpy", the NumPy reference. Read at each call.
BACKEND: str | None = None


def _kernel() -> Any:
    """`disco_cli._core` where BACKEND lets it compute the scores and it can, else None."""
    return compiled_core(BACKEND, "verify", "aligned_correlations")


def aligned_correlation(query: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Peak normalized circular cross-correlation [K] in [-1, 1] of query [R, S] with
    candidates [K, R, S], over all shifts along the last axis (each image centred first)."""
    q = np.asarray(query, dtype=np.float32)
    c = np.asarray(candidates, dtype=np.float32)
    if c.ndim != 3 or c.shape[1:] != q.shape:
        raise ValueError(
            f"query [R, S] and candidates [K, R, S] must agree: {q.shape} vs {c.shape}"
        )
    return aligned_correlations(q[None], c)[0]


def aligned_correlations(queries: np.ndarray, candidates: Any) -> np.ndarray:
    """`aligned_correlation` [V, K] of several query images [V, R, S] (a query and its
    side views) with candidates [K, R, S], or a list of K [R, S] images (rows held apart,
    as a cache holds them: the compiled core reads them where they lie). Each image's
    spectrum along sectors is taken once, and each frequency's cross-power of all pairs
    is one small matrix product."""
    # float32 is plenty: the scores are compared among a few dozen candidates.
    q = np.asarray(queries, dtype=np.float32)
    if isinstance(candidates, (list, tuple)):
        core = _kernel()
        if core is not None and q.ndim == 3 and q.shape[1] > 0 and q.shape[2] > 0:
            return core.aligned_correlations_at(q, candidates)
        candidates = np.stack(candidates) if candidates else np.zeros((0, *q.shape[1:]))
    c = np.asarray(candidates, dtype=np.float32)
    if q.ndim != 3 or c.ndim != 3 or c.shape[1:] != q.shape[1:]:
        raise ValueError(
            f"queries [V, R, S] and candidates [K, R, S] must agree: {q.shape} vs {c.shape}"
        )
    if len(q) == 0 or len(c) == 0:
        return np.zeros((len(q), len(c)), np.float32)
    core = _kernel()
    if core is not None and q.shape[1] > 0 and q.shape[2] > 0:
        return core.aligned_correlations(q, c)
    q = q - q.mean(axis=(1, 2), keepdims=True)
    c = c - c.mean(axis=(1, 2), keepdims=True)
    norms = np.outer(
        np.linalg.norm(q.reshape(len(q), -1), axis=1),
        np.linalg.norm(c.reshape(len(c), -1), axis=1),
    )
    # Spectra laid out [F, V, R] and [F, R, K] (the transposed FFT writes that layout
    # at no extra cost), so the products are one batched matrix multiply. conj(Q) C is
    # the conjugate of Q conj(C): its curve runs backwards, and has the same peak.
    fq = np.ascontiguousarray(np.conj(fft.rfft(q, axis=-1)).transpose(2, 0, 1))
    fc = fft.rfft(c.transpose(2, 1, 0), axis=0)
    curves = fft.irfft(np.matmul(fq, fc), n=q.shape[-1], axis=0)  # [S, V, K]
    # An empty image correlates with nothing: score it as unrelated rather than dividing by 0.
    score = np.where(norms > 0, curves.max(axis=0) / np.where(norms > 0, norms, 1.0), 0.0)
    return np.clip(score, -1.0, 1.0).astype(np.float32)  # rounding can step past 1 for a copy


def aligned_correlation_torch(query, candidates):
    """Differentiable `aligned_correlation` (training): query [B, R, S], candidates
    [B, n, R, S] -> [B, n]."""
    import torch  # deferred: torch costs ~1.5 s; only training needs it (queries use NumPy)

    q = query - query.mean(dim=(-2, -1), keepdim=True)
    c = candidates - candidates.mean(dim=(-2, -1), keepdim=True)
    norms = q.flatten(1).norm(dim=1)[:, None] * c.flatten(2).norm(dim=2) + 1e-9
    fq = torch.fft.rfft(q.float(), dim=-1)[:, None]
    fc = torch.fft.rfft(c.float(), dim=-1)
    curves = torch.fft.irfft((fq * torch.conj(fc)).sum(dim=-2), n=q.shape[-1], dim=-1)
    return curves.amax(dim=-1) / norms
