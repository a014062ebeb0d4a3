"""The U-Net's C++ steps (src/cpp/disco/conv3x3.*) and FrozenUNet's C++ path.

Truths: a plain convolution written here (np.einsum per tap, in float64, on an input
padded by hand), the max of each 2 x 2 block, the product row_w @ x @ col_w, FrozenUNet's
NumPy path (BLAS products) and torch's `unet.UNet` on the shipped weights.
Tolerance: the kernels sum float32 products in another order and fuse multiply-adds, so
they agree within 1e-5 of the output's scale (its largest magnitude), not exactly.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from conftest import kernel_level

from disco_cli import _core
from disco_cli.model import DEFAULT_WEIGHTS, load_model, npz_beside
from disco_cli.model.disco import default_model_config
from disco_cli.model.unet_numpy import FrozenUNet, _upsample_matrix, expected_shapes
from disco_cli.model.weights_npz import read_npz

LEVELS = {3: "avx512", 2: "avx2", 0: "plain"}
needs_default = pytest.mark.skipif(
    not npz_beside(DEFAULT_WEIGHTS).is_file(), reason="no shipped weights"
)


# Each kernel level the CPU has is forced in turn through the cap the BEV kernels
# share, so an AVX-512 machine checks the AVX2 and plain kernels too (level 1 runs
# the plain convolution, as 0 does).
@pytest.fixture(params=sorted(LEVELS, reverse=True), ids=list(LEVELS.values()))
def level(request):
    with kernel_level(request.param):
        assert _core._conv3x3_kernel_name() == LEVELS[request.param]
        yield request.param


def reference_conv(parts, weight, bias, circular, relu):
    """[cout, B, R, S] in float64: pad by hand, then one einsum per tap."""
    x = np.concatenate(parts, axis=0).astype(np.float64)
    c, b, r, s = x.shape
    padded = np.zeros((c, b, r + 2, s + 2))
    padded[:, :, 1:-1, 1:-1] = x
    if circular:
        padded[:, :, 1:-1, 0] = x[..., -1]
        padded[:, :, 1:-1, -1] = x[..., 0]
    out = np.broadcast_to(bias.astype(np.float64)[:, None, None, None], (len(bias), b, r, s))
    out = out.copy()
    for dy in range(3):
        for dx in range(3):
            tap = padded[:, :, dy : dy + r, dx : dx + s]
            out += np.einsum("oc,cbrs->obrs", weight[:, :, dy, dx].astype(np.float64), tap)
    return np.maximum(out, 0.0) if relu else out


CASES = [
    # parts' channels, cout, B, R, S
    ([20], 8, 1, 40, 120),  # the U-Net's first convolution
    ([64, 32], 32, 1, 10, 30),  # a skip connection
    ([5, 3], 11, 2, 5, 15),
    ([7], 3, 3, 3, 7),
    ([13, 6, 2], 17, 2, 4, 33),  # 33 sectors: two vectors and one lane of a third
    ([9], 5, 1, 2, 17),
    ([1], 1, 1, 1, 1),
    ([3], 9, 1, 6, 48),  # three whole AVX-512 vectors, six AVX2 ones
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: "x".join(map(str, c[2:])) + f"-{c[1]}")
def test_the_convolution_is_the_plain_one_at_every_level(level, case):
    channels, cout, b, r, s = case
    rng = np.random.default_rng(sum(channels) * 100 + cout)
    parts = [rng.standard_normal((c, b, r, s)).astype(np.float32) for c in channels]
    weight = rng.standard_normal((cout, sum(channels), 3, 3)).astype(np.float32)
    bias = rng.standard_normal(cout).astype(np.float32)
    conv = _core.Conv3x3(weight, bias)
    assert (conv.cout, conv.cin) == (cout, sum(channels))
    for circular in (True, False):
        scale = np.abs(reference_conv(parts, weight, bias, circular, False)).max()
        for relu in (True, False):
            out = conv(parts, circular, relu)
            assert out.shape == (cout, b, r, s) and out.dtype == np.float32
            want = reference_conv(parts, weight, bias, circular, relu)
            np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * scale)


def test_sectors_wrap_and_rings_do_not(level):
    """One lit cell in the last sector of the first ring: with circular padding it
    reaches sector 0 (through the right-hand tap), never the ring before (there is none)."""
    x = np.zeros((1, 1, 4, 10), np.float32)
    x[0, 0, 0, 9] = 1.0
    weight = np.zeros((1, 1, 3, 3), np.float32)
    weight[0, 0, 1, 2] = 2.0  # out[s] reads x[s + 1]
    conv = _core.Conv3x3(weight, np.zeros(1, np.float32))
    wrapped = conv([x], True, False)[0, 0]
    assert wrapped[0, 8] == 2.0 and wrapped[0, 9] == 0.0
    assert np.count_nonzero(wrapped) == 1
    zero = conv([x], False, False)[0, 0]
    assert zero[0, 8] == 2.0 and np.count_nonzero(zero) == 1


def test_pooling_and_the_separable_resize_at_the_unet_sizes():
    rng = np.random.default_rng(7)
    x = rng.standard_normal((16, 2, 20, 60)).astype(np.float32)
    pooled = _core.max_pool2(x)
    want = x.reshape(16, 2, 10, 2, 30, 2).max(axis=(3, 5))
    np.testing.assert_array_equal(pooled, want)
    odd = rng.standard_normal((3, 5, 7)).astype(np.float32)  # the last row and column dropped
    np.testing.assert_array_equal(
        _core.max_pool2(odd), odd[:, :4, :6].reshape(3, 2, 2, 3, 2).max(axis=(2, 4))
    )
    for circular, ac in ((True, False), (False, True)):
        rows = _upsample_matrix(20, False, ac).astype(np.float32)
        cols = _upsample_matrix(60, circular, ac).T.astype(np.float32)
        out = _core.resize_separable(x, rows, cols)
        want = np.einsum("ia,nbak,kj->nbij", rows, x.astype(np.float64), cols)
        np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * np.abs(want).max())
    # Dense weights (every output reads every input) take the general loop.
    rows = rng.standard_normal((9, 20)).astype(np.float32)
    cols = rng.standard_normal((60, 11)).astype(np.float32)
    want = np.einsum("ia,nbak,kj->nbij", rows, x.astype(np.float64), cols)
    out = _core.resize_separable(x, rows, cols)
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_bad_shapes_and_dtypes_are_value_errors():
    conv = _core.Conv3x3(np.ones((4, 3, 3, 3), np.float32), np.zeros(4, np.float32))
    x = np.ones((3, 1, 5, 15), np.float32)
    bad_inputs = [
        [],  # nothing
        [x[:2]],  # 2 channels, not 3
        [x[:2], np.ones((1, 1, 5, 14), np.float32)],  # sectors differ
        [x[:1], np.ones((2, 2, 5, 15), np.float32)],  # batch differs
        [x.astype(np.float64)],
        [x[0]],  # [B, R, S]
        [x[..., ::2]],  # not contiguous
        [x.tolist()],
    ]
    for inputs in bad_inputs:
        with pytest.raises(ValueError):
            conv(inputs, True, True)
    with pytest.raises(ValueError):
        _core.Conv3x3(np.ones((4, 3, 3, 2), np.float32), np.zeros(4, np.float32))
    with pytest.raises(ValueError):
        _core.Conv3x3(np.ones((4, 3, 3, 3), np.float32), np.zeros(5, np.float32))
    with pytest.raises(ValueError):
        _core.Conv3x3(np.ones((0, 3, 3, 3), np.float32), np.zeros(0, np.float32))
    with pytest.raises(ValueError):
        _core.resize_separable(x, np.ones((10, 4), np.float32), np.ones((15, 30), np.float32))
    with pytest.raises(ValueError):
        _core.resize_separable(x, np.ones((10, 5), np.float32), np.ones((14, 30), np.float32))
    with pytest.raises(ValueError):
        _core.max_pool2(np.ones(4, np.float32))
    # Empty batches are no error: an empty output.
    assert conv([np.ones((3, 0, 5, 15), np.float32)], True, True).shape == (4, 0, 5, 15)


def random_state(config: dict, seed: int) -> dict[str, np.ndarray]:
    """A U-Net state of `config`'s shapes, without torch: weights normal, BatchNorm
    statistics in a plausible range."""
    rng = np.random.default_rng(seed)
    std = 0.3 if config.get("norm", True) else 0.08
    state = {}
    for key, shape in expected_shapes(config).items():
        if key.endswith("running_var"):
            state[key] = rng.uniform(0.5, 2.0, shape).astype(np.float32)
        elif key.endswith("num_batches_tracked"):
            state[key] = np.array(0)
        else:
            state[key] = rng.normal(0.0, std, shape).astype(np.float32)
    return state


@pytest.mark.parametrize(
    "config",
    [
        default_model_config(20, 4),
        {"in_channels": 20, "width": 4, "norm": False, "circular": False, "sigmoid": True},
    ],
    ids=["project", "authors"],
)
def test_frozen_unet_in_cpp_computes_the_numpy_path(level, config):
    state = random_state(config, seed=5)
    cpp = FrozenUNet(state, config, backend="cpp")
    ref = FrozenUNet(state, config, backend="numpy")
    assert (cpp.backend, ref.backend) == ("cpp", "numpy")
    bevs = (np.random.default_rng(6).random((3, 20, 40, 120)) < 0.1).astype(np.float32)
    want = ref.correction(bevs)
    np.testing.assert_allclose(cpp.correction(bevs), want, rtol=0, atol=1e-5 * np.abs(want).max())


@needs_default
def test_the_shipped_model_runs_cpp_and_agrees_with_numpy_and_torch(level):
    torch = pytest.importorskip("torch")
    from disco_cli.model.checkpoint import read_checkpoint
    from disco_cli.model.disco import build_net

    model = load_model("default")
    assert model.net.backend == "cpp"  # the default where the core is built
    state, _ = read_npz(npz_beside(DEFAULT_WEIGHTS))
    ref = FrozenUNet({k: np.asarray(v) for k, v in state.items()}, model.model_config, "numpy")
    ckpt = read_checkpoint(DEFAULT_WEIGHTS)
    net = build_net(ckpt["model_config"])
    net.load_state_dict(ckpt["state_dict"])
    net.eval()
    bevs = (np.random.default_rng(8).random((2, 20, 40, 120)) < 0.15).astype(np.float32)
    out = model.net.correction(bevs)
    want = ref.correction(bevs)
    with torch.no_grad():
        truth = net.unet.correction(torch.from_numpy(bevs)).numpy().reshape(out.shape)
    scale = np.abs(truth).max()
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(out, truth, rtol=0, atol=1e-5 * scale)


def test_backend_choice_and_a_package_without_the_core():
    config = default_model_config(20, 4)
    state = random_state(config, seed=9)
    assert FrozenUNet(state, config).backend == "cpp"
    with pytest.raises(ValueError, match="backend"):
        FrozenUNet(state, config, backend="gpu")
    # Without the compiled core the NumPy path runs, and asking for C++ says why not.
    code = (
        "import sys; sys.modules['disco_cli._core'] = None\n"
        "import numpy as np\n"
        "from disco_cli.model.unet_numpy import FrozenUNet, expected_shapes\n"
        "from disco_cli.model.disco import default_model_config\n"
        "c = default_model_config(20, 4)\n"
        "s = {k: np.ones(v, np.float32) for k, v in expected_shapes(c).items()}\n"
        "print(FrozenUNet(s, c).backend)\n"
        "try:\n    FrozenUNet(s, c, backend='cpp')\n"
        "except ValueError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == [
        "numpy",
        "backend 'cpp' needs disco_cli._core, which is not built",
    ]
