"""The U-Net convolution's two algorithms (src/cpp/disco/conv3x3.cpp, direct, and
conv3x3_winograd.cpp, Winograd F(2 x 2, 3 x 3)), each forced, at every kernel level.

Truth: a direct convolution written here in float64 that pads nothing: each tap reads
the input at (ring + dy - 1, sector + dx - 1), sectors taken modulo S (circular) or
masked outside [0, S), rings masked outside [0, R). Tolerance: the kernels sum float32
products in other orders (Winograd through its transforms too), so they agree within
1e-5 of the output's largest magnitude, not exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_unet_kernel import random_state

from disco_cli import _core
from disco_cli.model.disco import default_model_config
from disco_cli.model.unet_numpy import FrozenUNet


def direct_reference(parts, weight, bias, circular, relu):
    """[cout, B, R, S] in float64, one shifted and masked copy of the input per tap."""
    x = np.concatenate(parts, axis=0).astype(np.float64)
    _, b, r, s = x.shape
    out = np.zeros((len(bias), b, r, s)) + bias.astype(np.float64)[:, None, None, None]
    rings, sectors = np.arange(r), np.arange(s)
    for dy in range(3):
        src_r = rings + dy - 1
        ok_r = (src_r >= 0) & (src_r < r)
        for dx in range(3):
            src_s = sectors + dx - 1
            ok_s = np.ones(s, bool) if circular else (src_s >= 0) & (src_s < s)
            tap = x[:, :, np.clip(src_r, 0, r - 1)][..., src_s % s]
            tap = tap * (ok_r[:, None] & ok_s[None, :])
            out += np.einsum("oc,cbrs->obrs", weight[:, :, dy, dx].astype(np.float64), tap)
    return np.maximum(out, 0.0) if relu else out


CASES = [
    # parts' channels, cout, B, R, S
    ([20], 8, 1, 40, 120),  # the U-Net's first convolution
    ([64, 32], 32, 3, 10, 30),  # a skip connection; more tiles than one block holds
    ([32], 64, 1, 5, 15),  # odd rings and sectors: partial tiles at both edges
    ([5, 3], 11, 3, 7, 50),  # 25 tile columns: a vector and one lane of the next
    ([13, 6, 2], 17, 2, 4, 33),
    ([4], 8, 1, 9, 97),  # 49 tile columns, odd sectors
    ([7], 3, 3, 3, 7),
    ([3], 9, 1, 2, 3),
    ([9], 5, 1, 1, 1),
]


@pytest.mark.parametrize("algorithm", ["direct", "winograd"])
@pytest.mark.parametrize("case", CASES, ids=lambda c: "x".join(map(str, c[2:])) + f"-{c[1]}")
def test_each_algorithm_is_the_plain_convolution_at_every_level(kernel, algorithm, case):
    channels, cout, b, r, s = case
    rng = np.random.default_rng(sum(channels) * 100 + cout + s)
    parts = [rng.standard_normal((c, b, r, s)).astype(np.float32) for c in channels]
    weight = rng.standard_normal((cout, sum(channels), 3, 3)).astype(np.float32)
    bias = rng.standard_normal(cout).astype(np.float32)
    conv = _core.Conv3x3(weight, bias)
    for circular in (True, False):
        plain = direct_reference(parts, weight, bias, circular, False)
        scale = np.abs(plain).max()
        for relu in (True, False):
            out = conv(parts, circular, relu, algorithm)
            assert out.shape == (cout, b, r, s) and out.dtype == np.float32
            want = np.maximum(plain, 0.0) if relu else plain
            np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * scale)


def test_the_reference_wraps_sectors_and_pads_rings():
    """The truth itself, on one lit cell: a kernel that reads the left neighbour moves
    it one sector right (around the end when circular); one reading the ring above
    moves it down a ring, and nothing comes in from outside the rings."""
    x = np.zeros((1, 1, 3, 4), np.float32)
    x[0, 0, 0, 3] = 1.0
    left = np.zeros((1, 1, 3, 3), np.float32)
    left[0, 0, 1, 0] = 1.0  # out[s] = x[s - 1]
    assert direct_reference([x], left, np.zeros(1), True, False)[0, 0, 0, 0] == 1.0
    assert not direct_reference([x], left, np.zeros(1), False, False).any()
    up = np.zeros((1, 1, 3, 3), np.float32)
    up[0, 0, 0, 1] = 1.0  # out[r] = x[r - 1]
    moved = direct_reference([x], up, np.zeros(1), True, False)[0, 0]
    assert moved[1, 3] == 1.0 and np.count_nonzero(moved) == 1


def test_auto_follows_the_documented_rule(kernel):
    conv = _core.Conv3x3(np.ones((8, 8, 3, 3), np.float32), np.zeros(8, np.float32))
    # conv3x3.cpp's prefers_winograd: AVX-512 from 256 cells, AVX2 from 64, plain never.
    name = _core._conv3x3_kernel_name()
    want = {
        "avx512": {(40, 120): "winograd", (10, 30): "winograd", (5, 15): "direct"},
        "avx2": {(40, 120): "winograd", (5, 15): "winograd", (3, 7): "direct"},
        "plain": {(40, 120): "direct", (5, 15): "direct"},
    }[name]
    for (r, s), algorithm in want.items():
        assert conv.choose(r, s) == algorithm, (name, r, s)


@pytest.mark.parametrize("algorithm", ["direct", "winograd"])
def test_the_unet_with_each_algorithm_computes_the_numpy_path(kernel, algorithm):
    config = default_model_config(20, 4)
    state = random_state(config, seed=11)
    cpp = FrozenUNet(state, config, backend="cpp")
    cpp.set_conv_algorithm(algorithm)
    ref = FrozenUNet(state, config, backend="numpy")
    bevs = (np.random.default_rng(12).random((3, 20, 40, 120)) < 0.1).astype(np.float32)
    want = ref.correction(bevs)
    np.testing.assert_allclose(cpp.correction(bevs), want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_an_unknown_algorithm_is_a_value_error():
    conv = _core.Conv3x3(np.ones((2, 3, 3, 3), np.float32), np.zeros(2, np.float32))
    x = np.ones((3, 1, 4, 6), np.float32)
    with pytest.raises(ValueError, match="'auto', 'direct' or 'winograd'"):
        conv([x], True, True, "fft")
    config = default_model_config(20, 4)
    net = FrozenUNet(random_state(config, seed=3), config, backend="cpp")
    with pytest.raises(ValueError, match="'auto', 'direct' or 'winograd'"):
        net.set_conv_algorithm("Winograd")
