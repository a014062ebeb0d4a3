"""The compiled search kernels against NumPy, at every SIMD level the CPU has: the exact
re-measure of candidate rows (`exact_topk`, src/cpp/disco/exact_search.*) and the int8
scan's dot products (the AVX-512 VNNI, AVX2 and plain kernels of int8_search.cpp)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import kernel_level

from disco_cli import _core
from disco_cli.maps.signature_index import (
    ProjectedSignatures,
    SignatureIndex,
    _exact_topk_numpy,
    exact_topk,
    smallest_per_row,
)


def _reference_topk(x: np.ndarray, q: np.ndarray, cand: np.ndarray, k: int):
    """Float64 distances of the given rows, sorted by (squared distance, row)."""
    c = cand[cand >= 0]
    sq = ((x[c].astype(np.float64) - q.astype(np.float64)) ** 2).sum(axis=1)
    order = np.lexsort((c, sq))[:k]
    return c[order], np.sqrt(sq[order])


def _check_topk(x, queries, cand, k, rows, dists) -> None:
    assert rows.shape == dists.shape == (len(queries), k)
    for i, q in enumerate(queries):
        want_r, want_d = _reference_topk(x, q, cand[i], k)
        np.testing.assert_array_equal(rows[i, : len(want_r)], want_r)
        np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12, atol=0)
        assert (rows[i, len(want_r) :] == -1).all() and np.isinf(dists[i, len(want_r) :]).all()


@pytest.mark.parametrize("dim", [1, 7, 31, 32, 33, 64, 100, 1024])
def test_exact_topk_equals_numpy(dim: int, kernel: int) -> None:
    # Widths below, at and past the 32 lanes; duplicate rows tie and go by row; -1
    # entries are no candidates; k from 1 to more than the candidates given.
    rng = np.random.default_rng(dim)
    x = rng.normal(size=(300, dim)).astype(np.float32)
    x[[10, 200, 250]] = x[5]
    queries = rng.normal(size=(3, dim)).astype(np.float32)
    queries[1] = x[5]  # four rows at distance 0
    others = rng.permutation(np.setdiff1d(np.arange(300), [5, 10, 200, 250]))[:56]
    cand = np.concatenate([[5, 250, 10, 200], others]).reshape(1, 60).repeat(3, axis=0)
    cand[0, ::7] = -1
    cand[2, :] = -1
    cand[2, 3] = 17
    for k in (1, 5, 60, 70):
        rows, dists = exact_topk(x, queries, cand, k)
        _check_topk(x, queries, cand, k, rows, dists)
    rows, _ = exact_topk(x, queries, cand, 3)
    np.testing.assert_array_equal(rows[1], [5, 10, 200])


def test_exact_kernels_give_the_same_bits(kernel: int) -> None:
    """Every level sums the same 32 lanes in the same tree: identical distances."""
    rng = np.random.default_rng(5)
    x = (rng.normal(size=(400, 1031)) * rng.uniform(0.01, 100, size=1031)).astype(np.float32)
    q = x[:2] + rng.normal(scale=1e-3, size=(2, 1031)).astype(np.float32)
    rows = np.arange(400, dtype=np.int64)
    got = _core.exact_sq_distances(x, q[0], rows)
    with kernel_level(0):
        plain = _core.exact_sq_distances(x, q[0], rows)
    np.testing.assert_array_equal(got, plain)
    want = ((x.astype(np.float64) - q[0].astype(np.float64)) ** 2).sum(axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)
    assert np.isinf(_core.exact_sq_distances(x, q[0], np.array([-1, 3]))[0])


def test_exact_topk_degenerate_rows(kernel: int) -> None:
    # All rows equal, all zero, a zero query: every distance ties, and rows decide.
    for x in (np.full((50, 16), 3.25, np.float32), np.zeros((50, 16), np.float32)):
        for q in (np.zeros((1, 16), np.float32), np.full((1, 16), -1.5, np.float32)):
            cand = np.array([[49, 3, 17, 0, -1, 8]])
            rows, dists = exact_topk(x, q, cand, 10)
            np.testing.assert_array_equal(rows[0], [0, 3, 8, 17, 49, -1, -1, -1, -1, -1])
            want = float(np.sqrt(((x[0].astype(np.float64) - q[0]) ** 2).sum()))
            assert (dists[0, :5] == want).all() and np.isinf(dists[0, 5:]).all()


def test_exact_topk_numpy_fallback_is_the_same(kernel: int) -> None:
    rng = np.random.default_rng(8)
    x = rng.normal(size=(200, 40)).astype(np.float32)
    queries = rng.normal(size=(2, 40)).astype(np.float32)
    cand = np.stack([rng.permutation(200)[:50], rng.permutation(200)[:50]])
    cand[1, ::3] = -1
    rows, dists = _exact_topk_numpy(x, queries, cand, 12)
    _check_topk(x, queries, cand, 12, rows, dists)
    core_rows, core_dists = exact_topk(x, queries, cand, 12)
    np.testing.assert_array_equal(core_rows, rows)
    np.testing.assert_allclose(core_dists, dists, rtol=1e-12, atol=0)


def test_exact_kernels_reject_bad_input() -> None:
    x = np.zeros((5, 4), np.float32)
    q = np.zeros((1, 4), np.float32)
    with pytest.raises(ValueError, match="below the row count"):
        _core.exact_topk(x, q, np.array([[5]]), 1)
    with pytest.raises(ValueError, match="below the row count"):
        _core.exact_sq_distances(x, q[0], np.array([0, 9]))
    with pytest.raises(ValueError):
        _core.exact_topk(x, np.zeros((1, 3), np.float32), np.array([[0]]), 1)
    with pytest.raises(ValueError):
        _core.exact_topk(x, q, np.array([[0], [1]]), 1)


@pytest.mark.parametrize("dim", [1, 63, 64, 65, 130, 1024])
def test_int8_dots_at_the_query_limit(dim: int, kernel: int) -> None:
    # g at +-int8_query_limit and around the VNNI kernel's split g = 256 hi + lo
    # (lo at +-128), against int64 NumPy; widths around its 64-code blocks.
    rng = np.random.default_rng(dim)
    codes = rng.integers(-127, 128, size=(50, dim)).astype(np.int8)
    codes[0], codes[1] = 127, -127
    top = _core.int8_query_limit(dim)
    edges = np.array([top, -top, 128, -128, 127, -127, 383, -383, 384, 0, 1, -1])
    g = np.clip(np.resize(edges, dim), -top, top)
    mixed = rng.random(dim) < 0.5
    g[mixed] = rng.integers(-top, top + 1, size=int(mixed.sum()))
    g = g.astype(np.int16)
    want = codes.astype(np.int64) @ g.astype(np.int64)
    np.testing.assert_array_equal(_core.int8_dots(codes, g, 1), want)
    np.testing.assert_array_equal(
        _core.int8_dots(codes, np.full(dim, top, np.int16), 2),
        codes.astype(np.int64).sum(axis=1) * top,
    )


def _cpu_flags() -> set[str]:
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.exists():
        return set()
    for line in cpuinfo.read_text().splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def test_each_level_runs_its_own_kernel(kernel: int) -> None:
    flags = _cpu_flags()
    if "avx2" not in flags:
        pytest.skip("the AVX2 and AVX-512 kernels are x86's")
    int8, exact, projected = _core.search_kernel_names()
    if kernel >= 3:
        assert exact == projected == "avx512"
        vnni = {"avx512f", "avx512bw", "avx512_vnni"} <= flags
        assert int8 == ("avx512vnni" if vnni else "avx2")
    elif kernel == 2:
        assert (int8, exact) == ("avx2", "avx2")
        assert projected == ("avx2" if "fma" in flags else "plain")
    else:
        assert (int8, exact, projected) == ("plain", "plain", "plain")


def _grid_signatures(kind: str, n: int, dim: int) -> np.ndarray:
    if kind == "equal":
        return np.full((n, dim), 0.75, np.float32)
    if kind == "zeros":
        return np.zeros((n, dim), np.float32)
    rng = np.random.default_rng(n)
    return np.abs(rng.normal(size=(n, dim))).astype(np.float32)


@pytest.mark.parametrize("kind", ["equal", "zeros", "random"])
def test_int8_search_with_limits_and_masks(kind: str, kernel: int) -> None:
    # The int8 scan and the exact re-measure together, at each level: row limits, an
    # exclusion mask, k above the rows allowed, and signatures that all tie.
    sigs = _grid_signatures(kind, 500, 96)
    rng = np.random.default_rng(2)
    queries = np.stack([sigs[3], np.zeros(96, np.float32), rng.random(96).astype(np.float32)])
    index = SignatureIndex(sigs, int8_min_rows=0)
    limit = np.array([500, 7, 120])
    exclude = rng.random((3, 500)) < 0.3
    for k in (1, 10, 600):
        rows, dists = index.search(queries, k, limit=limit, exclude=exclude)
        for i, q in enumerate(queries):
            allowed = np.flatnonzero((np.arange(500) < limit[i]) & ~exclude[i])
            want_r, want_d = _reference_topk(sigs, q, allowed, k)
            np.testing.assert_array_equal(rows[i, : len(want_r)], want_r)
            np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12, atol=0)
            assert (rows[i, len(want_r) :] == -1).all()


def test_projected_search_reranks_its_candidates_exactly(kernel: int) -> None:
    """The views' search: the `wide` rows nearest by projection (NumPy's selection),
    re-measured in float64 and cut to k, with a row limit and an exclusion mask."""
    rng = np.random.default_rng(6)
    sigs = np.abs(rng.normal(size=(3000, 64))).astype(np.float32)
    queries = np.abs(rng.normal(size=(4, 64))).astype(np.float32)
    proj = ProjectedSignatures(sigs, dims=16)
    limit = np.array([3000, 2000, 50, 3000])
    exclude = rng.random(3000) < 0.2
    rows, dists = proj.search(queries, 10, limit=limit, exclude=exclude)
    # The projections as one [p, N] matrix, multiplied by BLAS as before the tiles.
    projected_t = proj.tiles.transpose(1, 0, 2).reshape(16, -1)[:, :3000]
    approx = (queries - proj.mean) @ proj.axes @ projected_t * np.float32(-2.0) + proj.sq
    approx[np.arange(3000)[None] >= limit[:, None]] = np.inf
    approx[:, exclude] = np.inf
    cand = smallest_per_row(approx, 40)
    for i, q in enumerate(queries):
        c = cand[i][np.isfinite(approx[i, cand[i]])]
        want_r, want_d = _reference_topk(sigs, q, c, 10)
        np.testing.assert_array_equal(rows[i, : len(want_r)], want_r)
        np.testing.assert_allclose(dists[i, : len(want_d)], want_d, rtol=1e-12, atol=0)
        assert (rows[i, len(want_r) :] == -1).all()


@pytest.mark.parametrize(("n", "p", "b"), [(1, 1, 1), (63, 5, 2), (64, 96, 4), (1000, 96, 6)])
def test_projected_approx_same_bits_at_every_level(n: int, p: int, b: int, kernel: int) -> None:
    """The views' first pass: one fused multiply-add per axis in axis order on every
    level (the plain kernel's std::fma included), near the float64 value."""
    rng = np.random.default_rng(n + p)
    projected = rng.normal(size=(n, p)).astype(np.float32)
    tiles = np.zeros((-(-n // 64) * 64, p), np.float32)
    tiles[:n] = projected
    tiles = np.ascontiguousarray(tiles.reshape(-1, 64, p).transpose(0, 2, 1))
    sq = rng.uniform(10, 20, size=n).astype(np.float32)
    pq = rng.normal(size=(b, p)).astype(np.float32)
    got = _core.projected_approx(tiles, sq, pq)
    with kernel_level(0):
        plain = _core.projected_approx(tiles, sq, pq)
    np.testing.assert_array_equal(got, plain)
    want = sq - 2.0 * (pq.astype(np.float64) @ projected.T.astype(np.float64))
    scale = np.abs(pq).astype(np.float64) @ np.abs(projected.T).astype(np.float64) + sq
    assert (np.abs(got - want) <= 1e-5 * scale).all()
    with pytest.raises(ValueError, match="tiles"):
        _core.projected_approx(tiles, np.zeros(n + 64, np.float32), pq)
    with pytest.raises(ValueError, match="q must be"):
        _core.projected_approx(tiles, sq, np.zeros((b, p + 1), np.float32))


def _smallest_reference(values: np.ndarray, k: int) -> np.ndarray:
    """Each row's k smallest finite values' columns by a full sort on (value, column)."""
    out = np.full((len(values), k), -1, np.int64)
    for i, row in enumerate(values):
        cols = np.flatnonzero(np.isfinite(row))
        order = cols[np.lexsort((cols, row[cols]))][:k]
        out[i, : len(order)] = order
    return out


@pytest.mark.parametrize(
    ("n", "k"), [(1, 1), (7, 3), (10, 40), (300, 40), (10_000, 160), (40_001, 40)]
)
def test_compiled_smallest_per_row_equals_a_full_sort(n: int, k: int) -> None:
    """The views' first pass keeps each row's k smallest finite values, ties to the lower
    column, in (value, column) order; rows laid out against its sample (their lowest
    values between the sampled columns, or exactly on them) and rows with NaN, -inf and
    +inf (excluded rows) included."""
    rng = np.random.default_rng(n * 7 + k)
    cols = np.arange(n)
    rows = [
        rng.normal(size=n),
        cols[::-1].astype(float),  # the smallest at the end
        np.where(cols % 16 == 0, 0.0, 1.0) + rng.random(n) * 1e-3,  # samples lowest
        np.where(cols % 16 == 0, 1.0, 0.0) + rng.random(n) * 1e-3,  # samples highest
        np.round(rng.random(n) * 5),  # many ties
        np.full(n, np.inf),
    ]
    values = np.stack(rows).astype(np.float32)
    values[0, rng.integers(0, n, 5)] = np.inf
    values[4, rng.integers(0, n, 3)] = np.nan
    values[3, rng.integers(0, n, 3)] = -np.inf
    got = _core.smallest_per_row(values, k)
    np.testing.assert_array_equal(got, _smallest_reference(values, k))


def test_finite_smallest_per_row_without_the_core_finds_the_same_sets(monkeypatch) -> None:
    """The NumPy fallback (no compiled core) keeps the same columns, in its own order."""
    from disco_cli.maps import signature_index

    rng = np.random.default_rng(5)
    values = rng.normal(size=(3, 5000)).astype(np.float32)
    values[1, :4990] = np.inf  # fewer finite values than asked for
    want = _core.smallest_per_row(values, 40)
    monkeypatch.delattr(_core, "smallest_per_row")
    got = signature_index.finite_smallest_per_row(values, 40)
    for g, w in zip(got, want):
        assert sorted(g.tolist()) == sorted(w.tolist())
