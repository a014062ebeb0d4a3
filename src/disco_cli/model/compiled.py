"""Which code runs a model kernel: the compiled core's, or the NumPy reference.

`verify`, `yaw` and `yaw_refine` each keep their NumPy code as the reference the tests
compare the C++ kernels with, and as the fallback without the core. Each has a
module-level BACKEND (None: the core where it has the kernel; "numpy": the reference),
read at every call through `compiled_core`.
"""

from __future__ import annotations

from typing import Any


def compiled_core(backend: str | None, owner: str, *needs: str) -> Any:
    """`disco_cli._core` where `backend` (the BACKEND of module `owner`) lets it run and
    it has every kernel of `needs`, else None (the NumPy path)."""
    if backend == "numpy":
        return None
    if backend is not None:
        raise ValueError(f"{owner}.BACKEND must be None or 'numpy', not {backend!r}")
    try:
        # deferred: the package imports without the compiled core (a GPU training box)
        from disco_cli import _core
    except ImportError:
        return None
    return _core if all(hasattr(_core, name) for name in needs) else None
