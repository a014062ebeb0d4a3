"""The U-Net's forward pass without torch: C++ convolutions, or NumPy alone.

`FrozenUNet` computes what `unet.UNet` computes in eval mode, from the same state dict
(as NumPy arrays), with BatchNorm folded into the convolutions. Importing torch costs
about a second, more than the whole query, and torch's small convolutions and padding
copies cost more than their arithmetic. By default each 3 x 3 convolution, pooling and
upsampling runs in the compiled core (`_core.Conv3x3`, src/cpp/disco/conv3x3.cpp:
direct and register-blocked AVX-512 or AVX2 kernels, or Winograd's F(2 x 2, 3 x 3) where
the core measured it faster, conv3x3_winograd.cpp), about twice as fast as BLAS on
these small images. Without the core, on a CPU with neither (the plain C++ kernel is
slower than BLAS), or with `backend="numpy"` (the reference the tests and benchmarks
hold it to), each is one or a few BLAS products on a padded copy of its input, made
once per convolution with the concatenated skip connection written straight into it.

Activations are kept as [C, B, R, S]. A padded image [C, B, R + 2, S + 2] flattened to
[C, B * (R + 2) * (S + 2)] turns a kernel tap (dy, dx) into a shift of dy * (S + 2) + dx
along the flat axis, so a convolution is a sum of shifted matrix products; the outputs
that straddle a row's padding are computed and thrown away.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

_BN_EPS = 1e-5  # torch.nn.BatchNorm2d's default eps
_BLOCKS = (
    "dconv_down1",
    "dconv_down2",
    "dconv_down3",
    "dconv_down4",
    "dconv_up3",
    "dconv_up2",
    "dconv_up1",
)


def expected_shapes(model_config: Mapping[str, Any]) -> dict[str, tuple[int, ...]]:
    """The `unet.*` state dict entries of a configuration and their shapes, as torch's
    `UNet` has them (the yaw softmax `corr2soft.*` is not used at inference)."""
    c, w = int(model_config["in_channels"]), int(model_config["width"])
    norm = bool(model_config.get("norm", True))
    sizes = {
        "dconv_down1": (c, w),
        "dconv_down2": (w, 2 * w),
        "dconv_down3": (2 * w, 4 * w),
        "dconv_down4": (4 * w, 8 * w),
        "dconv_up3": (12 * w, 4 * w),
        "dconv_up2": (6 * w, 2 * w),
        "dconv_up1": (3 * w, w),
    }
    step = 3 if norm else 2
    shapes: dict[str, tuple[int, ...]] = {}
    for name, (cin, cout) in sizes.items():
        for i, a in ((0, cin), (step, cout)):
            shapes[f"unet.{name}.{i}.conv.weight"] = (cout, a, 3, 3)
            shapes[f"unet.{name}.{i}.conv.bias"] = (cout,)
            if norm:
                for part in ("weight", "bias", "running_mean", "running_var"):
                    shapes[f"unet.{name}.{i + 1}.{part}"] = (cout,)
                shapes[f"unet.{name}.{i + 1}.num_batches_tracked"] = ()
    shapes["unet.conv_last.weight"] = (1, w, 1, 1)
    shapes["unet.conv_last.bias"] = (1,)
    return shapes


def check_state(state: Mapping[str, np.ndarray], model_config: Mapping[str, Any]) -> None:
    """ValueError unless `state` holds exactly the U-Net of `model_config` (as torch's
    strict `load_state_dict` would say)."""
    shapes = expected_shapes(model_config)
    missing = sorted(set(shapes) - set(state))
    unexpected = sorted(k for k in state if k.startswith("unet.") and k not in shapes)
    if missing or unexpected:
        raise ValueError(f"missing keys {missing[:3]}, unexpected keys {unexpected[:3]}")
    for key, shape in shapes.items():
        if tuple(np.shape(state[key])) != shape:
            raise ValueError(f"{key} has shape {tuple(np.shape(state[key]))}, expected {shape}")


def _upsample_matrix(n: int, circular: bool, align_corners: bool) -> np.ndarray:
    """[2n, n] weights of torch's bilinear 2x upsampling along one axis: clamped at the
    ends, or (circular) as `unet.upsample2` does it on a copy padded by one on each side."""
    if circular:
        # upsample2: pad 1 circularly, upsample (align_corners=False), crop 2 each side.
        inner = _upsample_matrix(n + 2, False, False)[2:-2]
        wrapped = np.zeros((2 * n, n))
        src = (np.arange(n + 2) - 1) % n  # padded column -> original column
        np.add.at(wrapped.T, src, inner.T)
        return wrapped
    out = np.arange(2 * n, dtype=np.float64)
    if align_corners:
        pos = out * (n - 1) / max(2 * n - 1, 1)
    else:
        pos = np.maximum((out + 0.5) / 2 - 0.5, 0.0)
    lo = np.minimum(np.floor(pos).astype(int), n - 1)
    hi = np.minimum(lo + 1, n - 1)
    frac = pos - lo
    m = np.zeros((2 * n, n))
    np.add.at(m, (np.arange(2 * n), lo), 1.0 - frac)
    np.add.at(m, (np.arange(2 * n), hi), frac)
    return m


def compiled_core() -> Any:
    """`disco_cli._core` where it is built with the convolution, else None."""
    try:
        # deferred: the package imports without the compiled core (a GPU training box)
        from disco_cli import _core
    except ImportError:
        return None
    return _core if hasattr(_core, "Conv3x3") else None


def _has_simd_kernel(core: Any) -> bool:
    """Whether this CPU has the AVX-512 or AVX2 convolution (levels 3 and 2)."""
    return bool(core._conv3x3_kernel_name(3) or core._conv3x3_kernel_name(2))


class _Conv3x3:
    """A 3 x 3 convolution (BatchNorm folded in) with an optional ReLU; in C++ when
    given the compiled core, else in NumPy."""

    def __init__(self, weight: np.ndarray, bias: np.ndarray, core: Any = None):
        cout, cin = weight.shape[:2]
        self.cout, self.cin = cout, cin
        self.fast = None if core is None else core.Conv3x3(weight, bias)
        # The C++ algorithm: "auto" (the core's rule), or "direct" / "winograd" forced
        # (FrozenUNet.set_conv_algorithm: benchmarks and tests compare them).
        self.algorithm = "auto"
        # Taps stacked on the output axis: one product of [9 * cout, cin] with the input,
        # then nine shifted sums; cheaper than unrolling the input when cin > cout.
        self.by_tap = np.ascontiguousarray(
            weight.transpose(2, 3, 0, 1).reshape(9 * cout, cin), dtype=np.float32
        )
        # Taps stacked on the input axis, for an unrolled input [9 * cin, L].
        self.unrolled = np.ascontiguousarray(
            weight.transpose(0, 2, 3, 1).reshape(cout, 9 * cin), dtype=np.float32
        )
        self.bias = np.asarray(bias, np.float32)[:, None]

    def __call__(self, inputs: list[np.ndarray], circular: bool, relu: bool) -> np.ndarray:
        """Inputs [C_i, B, R, S] (concatenated along channels) -> [cout, B, R, S]."""
        if self.fast is not None:
            return self.fast(inputs, circular, relu, self.algorithm)
        _, b, r, s = inputs[0].shape
        padded = np.zeros((self.cin, b, r + 2, s + 2), np.float32)
        c0 = 0
        for x in inputs:
            c1 = c0 + x.shape[0]
            padded[c0:c1, :, 1:-1, 1:-1] = x
            if circular:
                padded[c0:c1, :, 1:-1, 0] = x[..., -1]
                padded[c0:c1, :, 1:-1, -1] = x[..., 0]
            c0 = c1
        flat = padded.reshape(self.cin, -1)
        row = s + 2
        n = flat.shape[1] - 2 * row - 2  # every output position whose taps stay inside
        out = np.empty((self.cout, flat.shape[1]), np.float32)
        acc = out[:, :n]
        offsets = [dy * row + dx for dy in range(3) for dx in range(3)]
        if self.cin > self.cout:
            z = self.by_tap @ flat
            np.add(z[: self.cout, :n], self.bias, out=acc)
            for k in range(1, 9):
                acc += z[k * self.cout : (k + 1) * self.cout, offsets[k] : offsets[k] + n]
        else:
            cols = np.empty((9, self.cin, n), np.float32)
            for k, off in enumerate(offsets):
                cols[k] = flat[:, off : off + n]
            np.matmul(self.unrolled, cols.reshape(9 * self.cin, n), out=acc)
            acc += self.bias
        if relu:
            np.maximum(acc, 0.0, out=acc)
        return out.reshape(self.cout, b, r + 2, s + 2)[:, :, :r, :s]


# Every key a model configuration may hold (checkpoint.py, disco.default_model_config,
# authors.py's "layout"). Another key is a misspelling or a newer network this NumPy
# U-Net does not know: refused, rather than run as something it is not.
MODEL_CONFIG_KEYS = frozenset(
    ("in_channels", "width", "norm", "circular", "sigmoid", "residual", "crop", "layout")
)


class FrozenUNet:
    """`unet.UNet.correction` in eval mode, without torch: [B, H, R, S] -> [B, R, S].

    `state` is a DiscoNet state dict as NumPy arrays (keys `unet.*`); `model_config`
    the checkpoint's (`norm`, `circular`, `sigmoid`). `backend`: "cpp" (the
    convolutions in the compiled core), "numpy" (BLAS products), or None for "cpp"
    where the core is built and the CPU has its AVX-512 or AVX2 kernel, else "numpy".
    KeyError or ValueError when the state does not fit, the configuration holds a key it
    does not know, or "cpp" is asked for without the core."""

    def __init__(
        self,
        state: Mapping[str, np.ndarray],
        model_config: Mapping[str, Any],
        backend: str | None = None,
    ):
        unknown = sorted(set(model_config) - MODEL_CONFIG_KEYS)
        if unknown:
            known = ", ".join(sorted(MODEL_CONFIG_KEYS))
            raise ValueError(f"model_config has unknown keys {', '.join(unknown)} (known: {known})")
        if backend not in (None, "cpp", "numpy"):
            raise ValueError(f"backend must be 'cpp' or 'numpy', not {backend!r}")
        core = None if backend == "numpy" else compiled_core()
        if backend is None and core is not None and not _has_simd_kernel(core):
            core = None  # the plain C++ kernel is about 2x slower than BLAS
        if backend == "cpp" and core is None:
            raise ValueError("backend 'cpp' needs disco_cli._core, which is not built")
        self._core = core
        self.backend = "numpy" if core is None else "cpp"
        self.norm = bool(model_config.get("norm", True))
        self.circular = bool(model_config.get("circular", True))
        self.sigmoid = bool(model_config.get("sigmoid", False))
        self.in_channels = int(model_config["in_channels"])
        check_state(state, model_config)
        self.blocks = {name: self._block(state, f"unet.{name}") for name in _BLOCKS}
        w = np.asarray(state["unet.conv_last.weight"], np.float32)
        self.last_w = w.reshape(w.shape[0], -1)[:1]
        self.last_b = np.asarray(state["unet.conv_last.bias"], np.float32).reshape(-1)[:1]
        self._up: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def set_conv_algorithm(self, algorithm: str) -> None:
        """Run the C++ convolutions as `algorithm`: "auto" (the default: Winograd where
        the core measured it faster than the direct kernel), "direct" or "winograd".
        ValueError for another name; the NumPy backend ignores it."""
        if algorithm not in ("auto", "direct", "winograd"):
            raise ValueError(f"algorithm must be 'auto', 'direct' or 'winograd', not {algorithm!r}")
        for convs in self.blocks.values():
            for conv in convs:
                conv.algorithm = algorithm

    def _block(self, state: Mapping[str, np.ndarray], prefix: str) -> list[_Conv3x3]:
        # torch's Sequential indices: conv, (BN), ReLU, conv, (BN), ReLU.
        step = 3 if self.norm else 2
        convs = []
        for i in (0, step):
            w = np.asarray(state[f"{prefix}.{i}.conv.weight"], np.float64)
            b = np.asarray(state[f"{prefix}.{i}.conv.bias"], np.float64)
            if self.norm:
                bn = f"{prefix}.{i + 1}"
                scale = np.asarray(state[f"{bn}.weight"], np.float64) / np.sqrt(
                    np.asarray(state[f"{bn}.running_var"], np.float64) + _BN_EPS
                )
                w = w * scale[:, None, None, None]
                b = (b - np.asarray(state[f"{bn}.running_mean"], np.float64)) * scale + (
                    np.asarray(state[f"{bn}.bias"], np.float64)
                )
            convs.append(_Conv3x3(w, b, self._core))
        return convs

    def _double(self, name: str, inputs: list[np.ndarray]) -> np.ndarray:
        first, second = self.blocks[name]
        return second([first(inputs, self.circular, True)], self.circular, True)

    def _upsample(self, x: np.ndarray) -> np.ndarray:
        c, b, r, s = x.shape
        if (r, s) not in self._up:
            # The authors' network (not circular) upsamples with align_corners=True.
            ac = not self.circular
            self._up[(r, s)] = (
                _upsample_matrix(r, False, ac).astype(np.float32),
                _upsample_matrix(s, self.circular, ac).T.astype(np.float32),
            )
            # Along rings the padding is zero and the ends clamp, as in F.interpolate.
        rows, cols = self._up[(r, s)]
        if self._core is not None:
            return self._core.resize_separable(x, rows, cols)
        y = (x.reshape(-1, s) @ cols).reshape(c * b, r, 2 * s)
        return np.matmul(rows, y).reshape(c, b, 2 * r, 2 * s)

    def _pool(self, x: np.ndarray) -> np.ndarray:
        """2 x 2 max-pooling: in C++, or the maximum of four strided views (a reduction
        over the reshaped pairs' axes was a third of the network's time)."""
        if self._core is not None:
            return self._core.max_pool2(x)
        out = np.maximum(x[..., 0::2, 0::2], x[..., 0::2, 1::2])
        np.maximum(out, x[..., 1::2, 0::2], out=out)
        return np.maximum(out, x[..., 1::2, 1::2], out=out)

    def correction(self, bevs: np.ndarray) -> np.ndarray:
        """The convolutional output [B, R, S] of BEVs [B, H, R, S] (float32)."""
        x = np.ascontiguousarray(np.asarray(bevs, np.float32).transpose(1, 0, 2, 3))
        c1 = self._double("dconv_down1", [x])
        c2 = self._double("dconv_down2", [self._pool(c1)])
        c3 = self._double("dconv_down3", [self._pool(c2)])
        y = self._double("dconv_down4", [self._pool(c3)])
        y = self._double("dconv_up3", [self._upsample(y), c3])
        y = self._double("dconv_up2", [self._upsample(y), c2])
        y = self._double("dconv_up1", [self._upsample(y), c1])
        c, b, r, s = y.shape
        out = (self.last_w @ y.reshape(c, -1) + self.last_b[:, None]).reshape(b, r, s)
        if self.sigmoid:
            out = 0.5 + 0.5 * np.tanh(0.5 * out)  # the logistic function, without overflow
        return out.astype(np.float32, copy=False)
