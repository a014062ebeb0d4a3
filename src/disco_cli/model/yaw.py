"""Yaw by phase correlation along the sector axis of two polar feature images.

For every ring, the normalized cross-power spectrum of the two rows (FFT along sectors)
is transformed back; the rings' curves are summed into one correlation curve over the
circular sector shift, each ring weighted by its radius (a translation of the sensor by t
turns a point at range r by about t / r, so far rings fix the angle better; the weights
sum to 1). Its peak is the shift that best aligns the two scans.

Sign convention (docs/architecture.md): if the query scan is the match scan rotated by
+a degrees, the query BEV is the match BEV rolled by +a / (360 / S) sectors, the curve
peaks at that shift, and the returned yaw is -a (the heading of the query sensor in the
match's frame, the yaw of T_match<-query).

Inference uses numpy/scipy (argmax and a parabolic sub-bin fit, batched over the K
candidates); training uses the torch version with the paper's learnable softmax. The
curves come from the compiled core (`_core.yaw_curves`, src/cpp/disco/sector_correlation.*)
where it has them; the NumPy code is the reference the tests compare it with
(`BACKEND = "numpy"`) and the fallback.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from disco_cli.io.poses.geometry import wrap_deg
from disco_cli.model import fft
from disco_cli.model.compiled import compiled_core

# Relative floor of the cross-power normalization: keeps empty rings and empty
# frequencies from turning into pure noise when divided by their own magnitude.
_EPS_REL = 1e-3

# Which code computes `correlation_curves`: None, the compiled kernel where the core has
# it, else NumPy; "numpy", the NumPy reference. Read at each call.
BACKEND: str | None = None


def _kernel() -> Any:
    """`disco_cli._core` where BACKEND lets it compute the curves and it can, else None."""
    return compiled_core(BACKEND, "yaw", "yaw_curves", "yaw_conf")


def ring_weights(rings: int) -> np.ndarray:
    """Weights [R] proportional to the ring's mean radius, summing to 1."""
    w = np.arange(rings, dtype=np.float64) + 0.5
    return w / w.sum()


@lru_cache(maxsize=8)
def ring_weights32(rings: int) -> np.ndarray:
    """`ring_weights` in float32 (read-only: kept between calls)."""
    w = ring_weights(rings).astype(np.float32)
    w.flags.writeable = False
    return w


def shift_to_yaw(shift: np.ndarray | float, sectors: int) -> np.ndarray:
    """Yaw in degrees of a query whose BEV is the match's rolled by `shift` sectors."""
    return wrap_deg(-np.asarray(shift, dtype=np.float64) * 360.0 / sectors)


def _checked(query: np.ndarray, matches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """query [R, S] and matches [K, R, S] (or one [R, S]) in float32, or one clear error."""
    q = np.asarray(query, dtype=np.float32)
    m = np.asarray(matches, dtype=np.float32)
    if m.ndim == 2:
        m = m[None]
    if q.ndim != 2 or m.ndim != 3 or m.shape[1:] != q.shape:
        raise ValueError(f"query [R, S] and matches [K, R, S] must agree: {q.shape} vs {m.shape}")
    return q, m


def correlation_curves(query: np.ndarray, matches: np.ndarray, workers: int = 1) -> np.ndarray:
    """Phase-correlation curves [K, S] of query [R, S] against matches [K, R, S]."""
    q, m = _checked(query, matches)
    core = _kernel()
    if core is not None and q.size > 0:
        return core.yaw_curves(q, m, ring_weights32(q.shape[0]))
    fq = fft.rfft(q, axis=-1, workers=workers)
    fm = fft.rfft(m, axis=-1, workers=workers)
    # float32 weights keep the spectra complex64 (float64 ones doubled the work).
    weights = ring_weights32(q.shape[0])
    return curves_of_cross_power(fq[None] * np.conj(fm), weights, q.shape[-1], workers)


def curves_of_cross_power(
    cross: np.ndarray, weights: np.ndarray, sectors: int, workers: int = 1
) -> np.ndarray:
    """Curves [K, S] from cross-power spectra [K, R, S // 2 + 1]: each whitened (divided
    by its magnitude plus a floor relative to its largest), rings summed with `weights`
    [R], transformed back."""
    mag = np.abs(cross)
    floor = _EPS_REL * mag.max(axis=(1, 2), keepdims=True) + 1e-12
    # One real factor per bin, weight / (|cross| + floor), and one complex product:
    # a complex division was 2.6x slower (0.36 vs 0.14 ms for 40 candidates).
    mag += floor
    np.divide(weights[None, :, None], mag, out=mag)
    return fft.irfft((cross * mag).sum(axis=1), n=sectors, axis=-1, workers=workers)


def peak_shift(curves: np.ndarray) -> np.ndarray:
    """Sub-bin peak positions [K] of circular curves [K, S] (argmax + parabola)."""
    k, s = curves.shape
    idx = np.argmax(curves, axis=1)
    rows = np.arange(k)
    c0 = curves[rows, idx]
    cm = curves[rows, (idx - 1) % s]
    cp = curves[rows, (idx + 1) % s]
    denom = cm - 2.0 * c0 + cp
    safe = np.where(np.abs(denom) > 1e-12, denom, -1.0)
    offset = np.where(np.abs(denom) > 1e-12, 0.5 * (cm - cp) / safe, 0.0)
    return idx + np.clip(offset, -0.5, 0.5)


def estimate_yaw(query: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """Yaw [K] in degrees, (-180, 180], of the query relative to each match."""
    curves = correlation_curves(query, matches)
    if len(curves) == 0:
        return np.zeros(0, np.float32)
    yaw = shift_to_yaw(peak_shift(curves), curves.shape[1]).astype(np.float32)
    # Rounding to float32 can turn -179.99999 into -180, which is outside (-180, 180].
    return np.where(yaw <= -180.0, np.float32(180.0), yaw)


# -- yaw confidence --------------------------------------------------------------------

# Peaks of a correlation curve closer than this to its best are the same peak.
SEPARATION_DEG = 20.0


def separation_bins(sectors: int) -> int:
    return max(1, int(round(SEPARATION_DEG * sectors / 360.0)))


def second_peak(curves: np.ndarray, best: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index [K], value [K]) of each curve's highest value more than SEPARATION_DEG from
    its sector `best` [K]: the strongest other heading (often the opposite one)."""
    k, s = curves.shape
    sep = separation_bins(s)
    d = np.abs((np.arange(s)[None] - np.asarray(best)[:, None] + s // 2) % s - s // 2)
    masked = np.where(d > sep, curves, -np.inf)
    idx = np.argmax(masked, axis=1)
    return idx, masked[np.arange(k), idx]


def margin(best: np.ndarray | float, other: np.ndarray | float) -> np.ndarray:
    """Yaw confidence in [0, 1]: 1 - other / best of two correlation peaks (0 where the
    other is as high as the best or the best is not positive)."""
    b = np.asarray(best, np.float64)
    o = np.maximum(np.asarray(other, np.float64), 0.0)
    conf = np.where(b > 0, 1.0 - o / np.where(b > 0, b, 1.0), 0.0)
    return np.clip(conf, 0.0, 1.0)


def estimate_yaw_conf(query: np.ndarray, matches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`estimate_yaw`'s yaw [K], its confidence [K]: the margin between the curve's best
    peak and its best other heading)."""
    q, m = _checked(query, matches)
    core = _kernel()
    if core is not None and q.size > 0:
        # The same curves, peaks and margins in C++ (the tests compare the two).
        return core.yaw_conf(q, m, ring_weights32(q.shape[0]), separation_bins(q.shape[1]))
    curves = correlation_curves(q, m)
    if len(curves) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    yaw = shift_to_yaw(peak_shift(curves), curves.shape[1]).astype(np.float32)
    best = np.argmax(curves, axis=1)
    _, other = second_peak(curves, best)
    conf = margin(curves[np.arange(len(curves)), best], other).astype(np.float32)
    return np.where(yaw <= -180.0, np.float32(180.0), yaw), conf


# -- differentiable version (training) ----------------------------------------


def correlation_curves_torch(query: Any, match: Any) -> Any:
    """Phase-correlation curves [B, S] of paired feature images [B, R, S] (torch)."""
    import torch  # deferred: torch costs ~1.5 s; only training needs it (queries use NumPy)

    fq = torch.fft.rfft(query.float(), dim=-1)
    fm = torch.fft.rfft(match.float(), dim=-1)
    cross = fq * torch.conj(fm)
    mag = cross.abs()
    floor = _EPS_REL * mag.amax(dim=(1, 2), keepdim=True).detach() + 1e-12
    w = torch.as_tensor(ring_weights(query.shape[1]), dtype=torch.float32, device=query.device)
    spec = (cross / (mag + floor) * w[None, :, None]).sum(dim=1)
    return torch.fft.irfft(spec, n=query.shape[-1], dim=-1)


def expected_shift_torch(prob: Any) -> Any:
    """Circular expectation of the shift under p(delta) [B, S], in sectors (-S/2, S/2]."""
    import torch  # deferred: torch costs ~1.5 s; only training needs it (queries use NumPy)

    s = prob.shape[-1]
    ang = torch.arange(s, device=prob.device, dtype=prob.dtype) * (2 * torch.pi / s)
    mean = torch.atan2((prob * torch.sin(ang)).sum(-1), (prob * torch.cos(ang)).sum(-1))
    return mean * s / (2 * torch.pi)
