"""The compiled real FFT along sectors (`_core.sector_rfft`, `_core.sector_irfft`):
numpy.fft's transforms in float32, the same values at every SIMD level."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import kernel_level

core = pytest.importorskip("disco_cli._core")
if not hasattr(core, "sector_rfft"):
    pytest.skip("the compiled core has no sector FFT", allow_module_level=True)

# The models' sector counts (120, 60), the tests' other grids (90, 121), powers of two,
# the radices alone, products of them, and primes the factors do not cover (a direct DFT).
LENGTHS = [1, 2, 3, 4, 5, 6, 8, 9, 12, 15, 16, 30, 60, 90, 120, 121, 127, 128, 7 * 11 * 2]


def error_bound(n: int, x: np.ndarray) -> float:
    """Float32 FFT error: a few float32 epsilons times log2(n) of the rows' energy."""
    scale = float(np.sqrt(n) * np.abs(x).max()) if x.size else 1.0
    return 8 * np.finfo(np.float32).eps * max(1.0, np.log2(n)) * scale


@pytest.mark.parametrize("n", LENGTHS)
def test_rfft_is_numpys_within_float32_error(n, kernel):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(37, n)).astype(np.float32)  # 37 rows: whole vectors and a tail
    got = core.sector_rfft(x)
    want = np.fft.rfft(x.astype(np.float64), axis=-1)
    assert got.dtype == np.complex64 and got.shape == want.shape
    assert np.abs(got - want).max() <= error_bound(n, x)
    # A real row's spectrum is real at 0 (and at n / 2 for even n): exactly.
    assert (got[:, 0].imag == 0).all()
    if n % 2 == 0:
        assert (got[:, n // 2].imag == 0).all()


@pytest.mark.parametrize("n", LENGTHS)
def test_irfft_is_numpys_within_float32_error(n, kernel):
    rng = np.random.default_rng(100 + n)
    half = n // 2 + 1
    # Any complex input, imaginary parts at 0 and n / 2 included: numpy ignores them.
    spec = (rng.normal(size=(21, half)) + 1j * rng.normal(size=(21, half))).astype(np.complex64)
    got = core.sector_irfft(spec, n)
    want = np.fft.irfft(spec.astype(np.complex128), n=n, axis=-1)
    assert got.dtype == np.float32 and got.shape == want.shape
    assert np.abs(got - want).max() <= error_bound(n, spec) / n * 4


@pytest.mark.parametrize("n", [60, 90, 120, 121])
def test_the_round_trip_gives_the_rows_back(n, kernel):
    x = np.random.default_rng(n).random((3, 5, n)).astype(np.float32)  # any leading shape
    back = core.sector_irfft(core.sector_rfft(x), n)
    assert back.shape == x.shape
    np.testing.assert_allclose(back, x, atol=2e-6)


@pytest.mark.parametrize("n", [120, 90, 121, 127])
def test_every_level_gives_the_same_values(n):
    rng = np.random.default_rng(7)
    x = rng.normal(size=(40, n)).astype(np.float32)
    spec = core.sector_rfft(x)
    results = {}
    for level in (0, 1, 2, 3):
        try:
            with kernel_level(level):
                results[level] = (core.sector_rfft(x), core.sector_irfft(spec, n))
        except pytest.skip.Exception:
            continue
    assert 0 in results and len(results) >= 2
    for level, (f, b) in results.items():
        np.testing.assert_array_equal(f, results[0][0], err_msg=f"level {level}")
        np.testing.assert_array_equal(b, results[0][1], err_msg=f"level {level}")


def test_bad_shapes_are_one_clear_error():
    with pytest.raises(ValueError, match="n // 2 \\+ 1"):
        core.sector_irfft(np.zeros((2, 60), np.complex64), 120)
    with pytest.raises(ValueError):
        core.sector_rfft(np.zeros((2, 0), np.float32))
    assert core.sector_rfft(np.zeros((0, 8), np.float32)).shape == (0, 5)
