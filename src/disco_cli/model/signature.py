"""Place signatures: |FFT2| of the polar feature image, centre low-pass crop, flattened.

A rotation of the sensor rolls the polar feature image along the sector axis, and the
magnitude of a Fourier spectrum does not see a circular shift, so the signature is
rotation invariant. Only the low-frequency centre is kept (the paper's LPF-1024 is
32 x 32): it holds the coarse layout of the place and drops high-frequency noise.

Signatures are L2-normalized. The quadruplet margins (0.5, 0.2) are meant for squared
distances on the unit sphere, and normalizing removes the dependence on how many points a
sensor returns (a 16-beam and a 64-beam scan of one place then compare).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from disco_cli.model import fft
from disco_cli.runtime.threads import get_threads

DEFAULT_CROP = (32, 32)


def crop_size(rings: int, sectors: int, crop: tuple[int, int] = DEFAULT_CROP) -> tuple[int, int]:
    """The crop actually used for a feature image of rings x sectors (never larger than it)."""
    return min(int(crop[0]), rings), min(int(crop[1]), sectors)


def _window(n: int, c: int) -> slice:
    # After fftshift the zero frequency sits at index n // 2; centre the crop on it.
    start = n // 2 - c // 2
    return slice(start, start + c)


@functools.lru_cache(maxsize=16)
def _crop_index(r: int, s: int, cr: int, cs: int) -> np.ndarray:
    """Where each cell of the crop [cr * cs] lies in the half spectrum [r, cs // 2 + 1]
    (flat): the crop's frequency (f1, f2), or (-f1, -f2) where f2 < 0 (a real image's
    spectrum is conjugate-symmetric, so the magnitude is the same there)."""
    f1 = np.arange(cr)[:, None] - cr // 2
    f2 = np.arange(cs)[None, :] - cs // 2
    row = np.where(f2 >= 0, f1, -f1) % r
    col = np.abs(f2)
    return (row * (cs // 2 + 1) + col).reshape(-1)


def signatures(
    features: np.ndarray, crop: tuple[int, int] = DEFAULT_CROP, workers: int | None = None
) -> np.ndarray:
    """Signatures [B, cr * cs] float32 of feature images [B, R, S] (or one [R, S]);
    the FFTs on `workers` threads (None: `disco_cli.get_threads()`).

    The crop's |FFT2| comes from the half spectrum along sectors: a real FFT along
    them, kept to the crop's cs // 2 + 1 lowest frequencies, then a complex FFT along
    rings of those columns alone (a third of the work of the full 2-D transform)."""
    g = np.asarray(features, dtype=np.float32)
    if g.ndim == 2:
        g = g[None]
    if g.ndim != 3:
        raise ValueError(f"features must be [B, R, S], got shape {g.shape}")
    b, r, s = g.shape
    cr, cs = crop_size(r, s, crop)
    if b == 0:
        return np.zeros((0, cr * cs), np.float32)
    if workers is None:
        workers = get_threads()
    half = fft.rfft(g, axis=2, workers=workers)[:, :, : cs // 2 + 1]
    spec = fft.fft(half, axis=1, workers=workers).reshape(b, -1)
    sig = np.abs(spec[:, _crop_index(r, s, cr, cs)])
    norm = np.linalg.norm(sig, axis=1, keepdims=True)
    return sig / np.maximum(norm, 1e-12)


def signatures_torch(features: Any, crop: tuple[int, int] = DEFAULT_CROP) -> Any:
    """The same signatures as `signatures`, differentiable, for training ([B, R, S] tensor)."""
    import torch  # deferred: torch costs ~1.5 s; only training needs it (queries use NumPy)

    b, r, s = features.shape
    cr, cs = crop_size(r, s, crop)
    spec = torch.fft.fftshift(torch.fft.fft2(features.float()), dim=(1, 2))
    mag = spec[:, _window(r, cr), _window(s, cs)].abs().reshape(b, -1)
    return torch.nn.functional.normalize(mag, dim=1, eps=1e-12)
