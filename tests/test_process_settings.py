"""Process settings for fast queries: one BLAS thread (blas_threads.py)."""

from __future__ import annotations

import pytest

from disco_cli.runtime.blas_threads import _functions, blas_threads


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
