"""The FFTs of a query (`rfft`, `irfft`, `fft`, `fft2`): SciPy's pocketfft, without `scipy.fft`.

`import scipy.fft` takes 0.2-0.5 s on the 2-core VM (it imports scipy.special and
SciPy's array-API layer, which imports numpy.f2py), a third of a one-scan
`disco query`; NumPy's own FFT is two to five times slower on these small float32
images. The transforms themselves are SciPy's compiled `pypocketfft`, loaded here
from its file without running `scipy/fft/__init__.py`, and registered under its own
name, so that a later `import scipy.fft` uses this same module.

Where that is not possible (another SciPy layout, SciPy already imported, any error),
the functions are `scipy.fft`'s. Same arguments and results as `scipy.fft` for what
this project uses: real or complex input in float32 or float64, one axis (or two for
`fft2`), the default normalization, `workers` as in SciPy.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

_NAME = "scipy.fft._pocketfft.pypocketfft"
_pocketfft: Any = None
_scipy_fft: Any = None


def _load() -> Any:
    """The pypocketfft module, or None (then scipy.fft is used)."""
    if "scipy.fft" in sys.modules:
        return None
    if _NAME in sys.modules:
        return sys.modules[_NAME]
    try:
        spec = importlib.util.find_spec("scipy")  # finds the folder, imports nothing
        if spec is None or not spec.submodule_search_locations:
            return None
        folder = Path(list(spec.submodule_search_locations)[0]) / "fft" / "_pocketfft"
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = folder / f"pypocketfft{suffix}"
            if path.is_file():
                break
        else:
            return None
        loader = importlib.machinery.ExtensionFileLoader(_NAME, str(path))
        ext_spec = importlib.util.spec_from_file_location(_NAME, path, loader=loader)
        if ext_spec is None:
            return None
        module = importlib.util.module_from_spec(ext_spec)
        loader.exec_module(module)
        for name in ("r2c", "c2r", "c2c"):
            if not callable(getattr(module, name, None)):
                return None
        sys.modules[_NAME] = module
        return module
    except Exception:  # any surprise: SciPy's public path below
        return None


def _backend() -> tuple[Any, Any]:
    """(pypocketfft or None, scipy.fft or None): one of them."""
    global _pocketfft, _scipy_fft
    if _pocketfft is None and _scipy_fft is None:
        _pocketfft = _load()
        if _pocketfft is None:
            # deferred: scipy.fft costs ~0.4 s; the fallback when pypocketfft cannot load
            import scipy.fft

            _scipy_fft = scipy.fft
    return _pocketfft, _scipy_fft


def _workers(workers: int | None) -> int:
    if workers is None:
        return 1
    if workers < 0:  # SciPy's meaning: -1 is every CPU, -2 all but one, ...
        return max(1, (os.cpu_count() or 1) + 1 + workers)
    return max(1, int(workers))


def _float(x: Any) -> np.ndarray:
    # scipy.fft keeps float32 and complex64, and computes everything else in double.
    a = np.asarray(x)
    if a.dtype in (np.float32, np.float64, np.complex64, np.complex128):
        return a
    return a.astype(np.complex128 if np.iscomplexobj(a) else np.float64)


def rfft(x: Any, axis: int = -1, workers: int | None = None) -> np.ndarray:
    pf, sf = _backend()
    if pf is None:
        return sf.rfft(x, axis=axis, workers=workers)
    a = _float(x)
    if np.iscomplexobj(a):
        raise TypeError("x must be a real sequence")
    return pf.r2c(a, (axis,), True, 0, None, _workers(workers))


def irfft(x: Any, n: int, axis: int = -1, workers: int | None = None) -> np.ndarray:
    pf, sf = _backend()
    if pf is None:
        return sf.irfft(x, n=n, axis=axis, workers=workers)
    a = _float(x)
    if not np.iscomplexobj(a):
        a = a + 0j
    m = n // 2 + 1  # the half spectrum that n real outputs need, cut or zero-padded
    if a.shape[axis] != m:
        index = [slice(None)] * a.ndim
        index[axis] = slice(0, min(m, a.shape[axis]))
        cut = a[tuple(index)]
        if cut.shape[axis] < m:
            pad = [(0, 0)] * a.ndim
            pad[axis] = (0, m - cut.shape[axis])
            cut = np.pad(cut, pad)
        a = cut
    return pf.c2r(a, (axis,), int(n), False, 2, None, _workers(workers))


def fft(x: Any, axis: int = -1, workers: int | None = None) -> np.ndarray:
    """The complex FFT along one axis (`scipy.fft.fft`)."""
    pf, sf = _backend()
    if pf is None:
        return sf.fft(x, axis=axis, workers=workers)
    return pf.c2c(_float(x), (axis,), True, 0, None, _workers(workers))


def fft2(x: Any, axes: tuple[int, int] = (-2, -1), workers: int | None = None) -> np.ndarray:
    pf, sf = _backend()
    if pf is None:
        return sf.fft2(x, axes=axes, workers=workers)
    return pf.c2c(_float(x), tuple(axes), True, 0, None, _workers(workers))


def backend() -> str:
    """Which implementation runs: 'pypocketfft' (loaded here) or 'scipy.fft'."""
    pf, _ = _backend()
    return "pypocketfft" if pf is not None else "scipy.fft"
