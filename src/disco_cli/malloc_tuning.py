"""Keep freed memory in the process (glibc), so that a query's arrays reuse mapped pages.

A query allocates and frees arrays of 0.1-2 MB (decoded features of 40 candidates,
the U-Net's activations, FFT buffers). glibc serves each of those with a fresh mmap and
returns it on free, or trims the heap after it; every page is then faulted in again on
the next query. On the 2-core VM of docs/benchmarks.md a fault costs so much that
reading the 40 candidates' features took 10.7 ms instead of 1.0 ms
(`benchmarks/bench_query.py` prints the ratio).

`keep_freed_memory()` raises the mmap threshold to 32 MiB and stops trimming (the
MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_ settings, made through mallopt): the
process keeps its peak heap, which for `disco query` is its working set anyway. It
is called by the command line only: a program that imports disco_cli keeps its own
allocator settings unless it calls this. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_MAX_SIZE = 32 * 1024 * 1024  # glibc's largest mmap threshold on 64-bit
_NEVER_TRIM = 2**31 - 1


def keep_freed_memory() -> bool:
    """True when glibc took the settings."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others have no mallopt
        return False
    mallopt.restype, mallopt.argtypes = ctypes.c_int, [ctypes.c_int, ctypes.c_int]
    ok = mallopt(_M_MMAP_THRESHOLD, _MMAP_MAX_SIZE) == 1
    return mallopt(_M_TRIM_THRESHOLD, _NEVER_TRIM) == 1 and ok
