"""How many threads NumPy's BLAS uses for a block of code (`blas_threads(n)`), without
extra packages.

NumPy's OpenBLAS splits even small matrix products over every core, and its threads
spin while they wait: on a busy 2-core machine the U-Net's small products then took
tens of milliseconds instead of two or three. The NumPy U-Net runs its products on
`disco_cli.get_threads()` threads (1 unless `--threads` says otherwise) whatever the
OpenBLAS was loaded with (`threads.set_threads` can only set its variable before it
loads).

The OpenBLAS that NumPy loaded is found in /proc/self/maps and asked through ctypes
(`openblas_set_num_threads_local`, which only touches the calling thread, where the
library has it; else the process-wide setter, restored afterwards). Where there is no
OpenBLAS (another BLAS, another OS) this does nothing.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy  # noqa: F401  (numpy loads its BLAS on import: _loaded_openblas finds it)

_LOCAL = "openblas_set_num_threads_local"
# Plain OpenBLAS, and the symbol-prefixed builds that NumPy and SciPy wheels bundle.
_GET = tuple(f"{p}_get_num_threads{s}" for p in ("openblas", "scipy_openblas") for s in ("", "64_"))
_SET = tuple(f"{p}_set_num_threads{s}" for p in ("openblas", "scipy_openblas") for s in ("", "64_"))

_libs: list[tuple[Any, Any, Any]] | None = None  # (set_local, get, set) per library


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries mapped into this process (Linux)."""
    paths: list[str] = []
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                path = line.split(maxsplit=5)[-1].strip()
                name = os.path.basename(path)
                if "openblas" in name and path.startswith("/") and path not in paths:
                    paths.append(path)
    except OSError:
        return []
    return paths


def _functions() -> list[tuple[Any, Any, Any]]:
    global _libs
    if _libs is None:
        found = []
        for path in _loaded_openblas():
            try:
                lib = ctypes.CDLL(path, mode=getattr(os, "RTLD_NOLOAD", 0) | os.RTLD_LAZY)
            except OSError:
                continue
            local = getattr(lib, _LOCAL, None)
            get = next((getattr(lib, n) for n in _GET if hasattr(lib, n)), None)
            put = next((getattr(lib, n) for n in _SET if hasattr(lib, n)), None)
            if local is not None:
                local.restype, local.argtypes = ctypes.c_int, [ctypes.c_int]
            if get is not None:
                get.restype, get.argtypes = ctypes.c_int, []
            if put is not None:
                put.restype, put.argtypes = None, [ctypes.c_int]
            if local is not None or (get is not None and put is not None):
                found.append((local, get, put))
        _libs = found
    return _libs


def one_blas_thread_for_process() -> bool:
    """NumPy's matrix products run on the calling thread from now on, in every thread,
    in a process that loaded NumPy before `threads.set_threads` could set its variable
    (benchmarks/bench_query.py does this to run as `disco` does). A product split over
    two threads once leaves OpenBLAS's workers spinning for a while after it, taking a
    core from whatever the process does next (a one-thread U-Net next to them ran 2-4x
    slower). True where an OpenBLAS took it."""
    done = False
    for _, _, put in _functions():
        if put is not None:
            put(1)
            done = True
    return done


@contextmanager
def blas_threads(n: int = 1) -> Iterator[None]:
    """Within the block, NumPy's matrix products run on `n` threads (1: the calling
    thread only)."""
    n = max(1, int(n))
    restore = []
    for local, get, put in _functions():
        if local is not None:
            restore.append((local, local(n)))
        else:
            restore.append((put, get()))
            put(n)
    try:
        yield
    finally:
        for setter, before in reversed(restore):
            setter(before)
