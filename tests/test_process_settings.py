"""Process settings for fast queries: one BLAS thread (blas_threads.py) and glibc
keeping freed memory (malloc_tuning.py)."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest
from conftest import package_path

from disco_cli.blas_threads import _functions, blas_threads


def test_blas_threads_sets_and_restores():
    getters = [get for _, get, _ in _functions() if get is not None]
    if not getters:
        pytest.skip("NumPy here does not use an OpenBLAS that tells its thread count")
    before = [get() for get in getters]
    with blas_threads(1):
        assert [get() for get in getters] == [1] * len(getters)
        if min(before) >= 2:  # a library loaded with one thread may not start more
            with blas_threads(2):
                assert [get() for get in getters] == [2] * len(getters)
            assert [get() for get in getters] == [1] * len(getters)
    assert [get() for get in getters] == before


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_keep_freed_memory_keeps_a_freed_block_mapped():
    """In a fresh process: a 4 MiB array freed and allocated again comes back at the
    same address from the heap once the settings are made; glibc's own default
    (mmap per block, unmapped on free) is the contrast, checked in the same run."""
    code = (
        "import numpy as np, sys\n"
        "from disco_cli.malloc_tuning import keep_freed_memory\n"
        "def mapped():\n"
        "    a = np.ones(1 << 20, np.float32); p = a.ctypes.data; del a\n"
        "    with open('/proc/self/maps') as fh:\n"
        "        return any(int(l.split('-')[0], 16) <= p < int(l.split()[0].split('-')[1], 16)\n"
        "                   for l in fh)\n"
        "before = mapped()\n"
        "print(keep_freed_memory(), before, mapped())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={"PYTHONPATH": package_path()},
        check=True,
    )
    took, before, after = out.stdout.split()
    assert took == "True"
    assert before == "False"  # glibc's default: the freed block was unmapped
    assert after == "True"  # kept: the next query's arrays find their pages mapped
