"""Exact search: the same rows and distances as a plain float64 NumPy brute force."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from conftest import KERNEL_LEVELS, kernel_level

from disco_cli.query.search import SignatureIndex

# Both first passes: the float32 BLAS product, and the compiled int8 scan, the latter at
# each SIMD kernel level the CPU has (its AVX2 and plain kernels must find the same rows).
PASSES = {"blas": {"int8_min_rows": 10**12}, "int8": {"int8_min_rows": 0}}
FIRST_PASSES = [("blas", None)] + [("int8", level) for level in KERNEL_LEVELS]


@pytest.fixture(
    params=FIRST_PASSES,
    ids=[name if level is None else f"int8-{KERNEL_LEVELS[level]}" for name, level in FIRST_PASSES],
)
def first_pass(request: pytest.FixtureRequest) -> Iterator[dict]:
    name, level = request.param
    if level is None:
        yield PASSES[name]
        return
    with kernel_level(level):
        yield PASSES[name]


def _truth(sigs: np.ndarray, q: np.ndarray, k: int, allowed: np.ndarray | None = None):
    d = np.sqrt(((sigs.astype(np.float64) - q.astype(np.float64)) ** 2).sum(1))
    if allowed is not None:
        d = np.where(allowed, d, np.inf)
    order = np.argsort(d, kind="stable")
    order = order[np.isfinite(d[order])][:k]
    return order, d[order]


@pytest.mark.parametrize("n,dim,k", [(1, 8, 1), (50, 16, 5), (2000, 64, 10), (500, 256, 500)])
def test_search_equals_brute_force(n: int, dim: int, k: int, first_pass: dict) -> None:
    rng = np.random.default_rng(n + dim)
    sigs = rng.normal(size=(n, dim)).astype(np.float32)
    queries = rng.normal(size=(7, dim)).astype(np.float32)
    index = SignatureIndex(sigs, **first_pass)
    assert (index._codes is not None) == (first_pass["int8_min_rows"] == 0)
    rows, dists = index.search(queries, k)
    for i, q in enumerate(queries):
        want_rows, want_d = _truth(sigs, q, k)
        np.testing.assert_array_equal(rows[i, : len(want_rows)], want_rows)
        np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12)
        assert (rows[i, len(want_rows) :] == -1).all()


def test_near_ties_with_large_common_offset(first_pass: dict) -> None:
    # Signatures like spectra: a large shared component and tiny differences, where the
    # float32 expansion ||q||^2 - 2 q.d + ||d||^2 alone misorders rows.
    rng = np.random.default_rng(3)
    base = rng.uniform(50, 100, size=512).astype(np.float32)
    sigs = (base + rng.normal(scale=1e-2, size=(3000, 512))).astype(np.float32)
    queries = (base + rng.normal(scale=1e-2, size=(5, 512))).astype(np.float32)
    rows, dists = SignatureIndex(sigs, **first_pass).search(queries, 10)
    for i, q in enumerate(queries):
        want_rows, want_d = _truth(sigs, q, 10)
        np.testing.assert_array_equal(rows[i], want_rows)
        np.testing.assert_allclose(dists[i], want_d, rtol=1e-12)


def test_exact_duplicates_tie_break_by_row(first_pass: dict) -> None:
    sigs = np.zeros((6, 4), np.float32)
    sigs[[1, 4]] = 1.0
    rows, dists = SignatureIndex(sigs, **first_pass).search(np.ones(4, np.float32), 3)
    np.testing.assert_array_equal(rows, [1, 4, 0])
    np.testing.assert_allclose(dists, [0.0, 0.0, 2.0])


def test_limit_and_exclude_mask(first_pass: dict) -> None:
    rng = np.random.default_rng(1)
    sigs = rng.normal(size=(300, 32)).astype(np.float32)
    queries = rng.normal(size=(4, 32)).astype(np.float32)
    limit = np.array([0, 3, 100, 300])
    exclude = rng.random((4, 300)) < 0.5
    rows, dists = SignatureIndex(sigs, **first_pass).search(
        queries, 5, limit=limit, exclude=exclude
    )
    for i, q in enumerate(queries):
        allowed = (np.arange(300) < limit[i]) & ~exclude[i]
        want_rows, want_d = _truth(sigs, q, 5, allowed)
        np.testing.assert_array_equal(rows[i, : len(want_rows)], want_rows)
        np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12)
        assert (rows[i, len(want_rows) :] == -1).all()
        assert np.isinf(dists[i, len(want_rows) :]).all()


def test_rejects_bad_shapes() -> None:
    index = SignatureIndex(np.zeros((3, 4), np.float32))
    with pytest.raises(ValueError):
        index.search(np.zeros((2, 5), np.float32), 1)
    with pytest.raises(ValueError):
        SignatureIndex(np.full((2, 2), np.nan, np.float32))


def test_int8_pass_constant_dimensions_and_far_queries(kernel: int) -> None:
    # A constant column (scale 0), values far from the map, and k above the row count.
    rng = np.random.default_rng(7)
    sigs = rng.normal(size=(700, 40)).astype(np.float32)
    sigs[:, 3] = 2.5
    queries = np.concatenate([rng.normal(size=(3, 40)), 50 + rng.normal(size=(2, 40))])
    queries = queries.astype(np.float32)
    index = SignatureIndex(sigs, int8_min_rows=0)
    for k in (1, 10, 800):
        rows, dists = index.search(queries, k)
        for i, q in enumerate(queries):
            want_rows, want_d = _truth(sigs, q, k)
            np.testing.assert_array_equal(rows[i, : len(want_rows)], want_rows)
            np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12)


def test_int8_bounds_hold_for_every_row(kernel: int) -> None:
    # The kernel's candidates must include every row whose true distance is within the
    # k-th smallest: check the bound directly on near-duplicate rows (tight spacing).
    from disco_cli import _core

    rng = np.random.default_rng(11)
    base = rng.random(256).astype(np.float32)
    sigs = (base + rng.normal(scale=1e-3, size=(5000, 256))).astype(np.float32)
    index = SignatureIndex(sigs, int8_min_rows=0)
    q = (base + rng.normal(scale=1e-3, size=256)).astype(np.float32)
    cand = index._codes.candidates(q, 10, len(sigs), None, 2)
    d = np.sqrt(((sigs.astype(np.float64) - q) ** 2).sum(1))
    kth = np.sort(d)[9]
    assert set(np.flatnonzero(d <= kth)) <= set(cand.tolist())
    assert len(cand) < len(sigs) // 2  # and it does prune
    g = rng.integers(-16000, 16000, 256).astype(np.int16)
    np.testing.assert_array_equal(
        _core.int8_dots(index._codes.codes, g, 2),
        index._codes.codes.astype(np.int64) @ g.astype(np.int64),
    )


def test_degenerate_signatures_fall_back_and_stay_exact(kernel: int) -> None:
    # Rows that differ far below the int8 step: the bounds cannot prune.
    rng = np.random.default_rng(4)
    base = rng.random(64).astype(np.float32)
    sigs = np.repeat(base[None], 6000, axis=0)
    sigs[:, 0] += rng.normal(scale=1e-6, size=6000).astype(np.float32)
    sigs[::7] += 1.0  # a few distinct rows keep the int8 range wide
    q = base + np.float32(1e-7)
    index = SignatureIndex(sigs, int8_min_rows=0)
    assert len(index._codes.candidates(q, 5, len(sigs), None, 1)) > len(sigs) // 8
    rows, dists = index.search(q, 5)
    want_rows, want_d = _truth(sigs, q, 5)
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_allclose(dists, want_d, rtol=1e-9)


@pytest.mark.parametrize("n,dim", [(1, 1), (40, 15), (300, 16), (1000, 37), (64, 256)])
def test_int8_codes_and_dots_equal_numpy(n: int, dim: int, kernel: int) -> None:
    # The encoder's definition (int8_search.hpp) and g . c, written in NumPy: float64
    # codes and sums, int64 dots. Widths below, at and past the AVX2 kernels' 16 lanes.
    from disco_cli import _core

    rng = np.random.default_rng(n * dim)
    x = (rng.normal(size=(n, dim)) * rng.uniform(0.1, 10.0, size=dim)).astype(np.float32)
    mean = x.mean(axis=0, dtype=np.float64)
    spread = np.abs(x - mean).max(axis=0)
    scale = np.where(spread > 0, spread / 127.0, 1.0)
    codes, code_sq, code_norm, err = _core.int8_encode(x, mean, scale, 2)
    centred = x.astype(np.float64) - mean
    want = np.rint(np.clip(centred * (1.0 / scale), -127.0, 127.0))
    np.testing.assert_array_equal(codes, want.astype(np.int8))
    np.testing.assert_allclose(code_sq, ((want * scale) ** 2).sum(1), rtol=1e-12)
    np.testing.assert_allclose(code_norm, np.sqrt((want**2).sum(1)), rtol=1e-12)
    np.testing.assert_allclose(err, np.sqrt(((centred - want * scale) ** 2).sum(1)), rtol=1e-12)
    g = rng.integers(-_core.int8_query_limit(dim), _core.int8_query_limit(dim), dim)
    np.testing.assert_array_equal(
        _core.int8_dots(codes, g.astype(np.int16), 2), codes.astype(np.int64) @ g
    )


@pytest.mark.parametrize(
    ("n", "k"),
    [(n, k) for n in (10, 300, 10_000, 40_001) for k in (1, 40, 160) if k <= n],
)
def test_smallest_per_row_finds_what_argpartition_finds(n: int, k: int) -> None:
    """The views' first pass: each row's k smallest values, against a full sort."""
    from disco_cli.maps.signature_index import smallest_per_row

    rng = np.random.default_rng(n + k)
    rows = [
        rng.normal(size=n),
        np.arange(n, dtype=float)[::-1],  # the smallest at the end, between samples
        np.where(np.arange(n) % 16 == 0, 0.0, 1.0) + rng.random(n) * 1e-3,  # samples lowest
        np.where(np.arange(n) % 16 == 0, 1.0, 0.0) + rng.random(n) * 1e-3,  # samples highest
        np.full(n, np.inf),
    ]
    values = np.stack(rows).astype(np.float32)
    values[0, rng.integers(0, n, 5)] = np.inf  # excluded rows
    got = smallest_per_row(values, k)
    assert got.shape == (len(rows), k)
    for row, idx in zip(values, got):
        assert len(set(idx.tolist())) == k
        assert np.array_equal(np.sort(row[idx]), np.sort(row)[:k])
