"""How many CPU threads disco computes on: `--threads N`, else `DISCO_THREADS`, else 1.

One setting for every pool disco starts: the threads that read and voxelize scans
(one scan each, so work is spread across scans), torch's intra-op threads, the C++
search and voxelizer, scipy's FFTs, and the BLAS/OpenMP libraries. The default is 1
because a robot's CPU is shared: with two threads per forward pass, a query stream
beside one busy process ran 1.96x slower than idle, with one thread 1.0x (issue 23),
and one thread was as fast on the idle machine.

Call `set_threads` before the first torch op: torch reads `OMP_NUM_THREADS` when it
is imported, and `torch.set_num_threads` covers the case where it is imported already.
BLAS libraries read their variables only when they load, so a library already loaded
(numpy's OpenBLAS in a program that imported numpy first) keeps its own threads.
"""

from __future__ import annotations

import os
import sys

from disco_cli.errors import DiscoError

ENV = "DISCO_THREADS"
DEFAULT = 1
# Read by OpenMP (torch's intra-op pool among them) and the BLAS libraries as they load.
_LIBRARY_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

_current: int | None = None


def parse_threads(value: object, source: str) -> int:
    """A thread count from `source` (an option or a variable), or one DiscoError line."""
    if isinstance(value, bool):
        raise DiscoError(f"{source}: {value!r} is not a whole number of threads (1 or more)")
    try:
        n = int(str(value).strip())
    except ValueError:
        raise DiscoError(
            f"{source}: {value!r} is not a whole number of threads (1 or more)"
        ) from None
    if n < 1:
        raise DiscoError(f"{source}: {n} threads; give 1 or more")
    return n


def resolve_threads(given: int | None = None) -> int:
    """`given` (from --threads or the API), else `DISCO_THREADS`, else 1."""
    if given is not None:
        return parse_threads(given, "threads")
    env = os.environ.get(ENV)
    if env is not None and env.strip() != "":
        return parse_threads(env, ENV)
    return DEFAULT


def set_threads(n: int | None = None) -> int:
    """Compute on `n` threads from now on (None: `DISCO_THREADS`, else 1); returns n.

    Sets torch's intra-op threads (now if torch is loaded, else through
    OMP_NUM_THREADS when it loads) and the default of every disco thread pool."""
    global _current
    n = resolve_threads(n)
    for var in _LIBRARY_ENV:
        os.environ[var] = str(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
        try:  # legal only before torch's first inter-op work; then it keeps its pool
            torch.set_num_interop_threads(n)
        except RuntimeError:
            pass
    _current = n
    return n


def get_threads() -> int:
    """The thread count in force: the last `set_threads`, else `DISCO_THREADS`, else 1."""
    return _current if _current is not None else resolve_threads(None)


def ensure_threads() -> int:
    """Apply the setting once if nothing has yet (a Python program that never called
    `set_threads`): the library then runs as the command line does."""
    return _current if _current is not None else set_threads(None)
