"""disco_cli.model.fft (SciPy's pocketfft without importing scipy.fft) against
scipy.fft itself, in a fresh interpreter where scipy.fft was never imported."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import scipy.fft
from conftest import package_path

_CODE = """
import sys
import numpy as np
from disco_cli.model import fft
rng = np.random.default_rng(0)
out = {"backend": np.array(fft.backend())}
for dtype in (np.float32, np.float64):
    x = rng.normal(size=(3, 40, 120)).astype(dtype)
    out[f"x_{dtype.__name__}"] = x
    out[f"rfft_{dtype.__name__}"] = fft.rfft(x, axis=-1)
    out[f"rfft0_{dtype.__name__}"] = fft.rfft(x, axis=1)
    out[f"fft2_{dtype.__name__}"] = fft.fft2(x, axes=(1, 2), workers=-1)
    spec = fft.rfft(x, axis=-1)
    out[f"irfft_{dtype.__name__}"] = fft.irfft(spec, n=120, axis=-1)
    out[f"irfft_odd_{dtype.__name__}"] = fft.irfft(spec, n=119, axis=-1)
    out[f"irfft_long_{dtype.__name__}"] = fft.irfft(spec, n=130, axis=-1)
out["scipy_fft_loaded"] = np.array("scipy.fft" in sys.modules)
import scipy.fft  # afterwards, as training would: the same module serves both
out["after"] = scipy.fft.rfft(out["x_float32"], axis=-1)
np.savez(sys.argv[1], **out)
"""


def test_pocketfft_without_scipy_fft_matches_scipy_fft(tmp_path):
    path = tmp_path / "out.npz"
    subprocess.run(
        [sys.executable, "-c", _CODE, str(path)],
        check=True,
        env={"PYTHONPATH": package_path()},
    )
    out = np.load(path)
    assert str(out["backend"]) == "pypocketfft"
    assert not bool(out["scipy_fft_loaded"])
    for name in ("float32", "float64"):
        x = out[f"x_{name}"]
        tol = 1e-4 if name == "float32" else 1e-10
        pairs = {
            "rfft": scipy.fft.rfft(x, axis=-1),
            "rfft0": scipy.fft.rfft(x, axis=1),
            "fft2": scipy.fft.fft2(x, axes=(1, 2)),
            "irfft": scipy.fft.irfft(scipy.fft.rfft(x, axis=-1), n=120, axis=-1),
            "irfft_odd": scipy.fft.irfft(scipy.fft.rfft(x, axis=-1), n=119, axis=-1),
            "irfft_long": scipy.fft.irfft(scipy.fft.rfft(x, axis=-1), n=130, axis=-1),
        }
        for key, ref in pairs.items():
            got = out[f"{key}_{name}"]
            assert got.dtype == ref.dtype and got.shape == ref.shape, key
            np.testing.assert_allclose(got, ref, atol=tol * np.abs(ref).max(), err_msg=key)
    # The round trip is the identity (an independent check of the normalization).
    np.testing.assert_allclose(out["irfft_float64"], out["x_float64"], atol=1e-12)
    np.testing.assert_allclose(out["after"], out["rfft_float32"], atol=1e-4 * 120)
