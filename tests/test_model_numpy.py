"""The NumPy U-Net (unet_numpy.py) against torch's, the torch-free weights file, and a
query path that never imports torch.

Truth: torch's own UNet in eval mode on the same weights. Tolerances: features within
1e-4 of torch's (float32 products summed in another order; the shipped model's
features reach about 15), signatures within 1e-5 (they are unit vectors), yaw within
0.01 degree.
"""

from __future__ import annotations

import subprocess
import sys
import zipfile

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import package_path  # noqa: E402

from disco_cli.errors import ModelError  # noqa: E402
from disco_cli.io.readers import list_scans, read_scan  # noqa: E402
from disco_cli.model import DEFAULT_WEIGHTS, load_model, npz_beside  # noqa: E402
from disco_cli.model.bev import BEVConfig, polar_bev  # noqa: E402
from disco_cli.model.checkpoint import read_checkpoint  # noqa: E402
from disco_cli.model.disco import DiscoModel, build_net, default_model_config  # noqa: E402
from disco_cli.model.unet_numpy import FrozenUNet  # noqa: E402
from disco_cli.model.weights_npz import file_sha256, read_npz, save_npz  # noqa: E402

H, R, S = 20, 40, 120
needs_default = pytest.mark.skipif(
    not npz_beside(DEFAULT_WEIGHTS).is_file(), reason="no shipped weights"
)


def random_net(config: dict, seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    net = build_net(config)
    # Without BatchNorm the activations grow layer by layer: smaller weights keep the
    # sigmoid's input where its output still tells the two apart.
    std = 0.3 if config.get("norm", True) else 0.08
    with torch.no_grad():
        for p in net.parameters():  # also the residual model's zero last layer
            p.normal_(0.0, std)
        for mod in net.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                mod.running_mean.uniform_(-0.2, 0.2)
                mod.running_var.uniform_(0.5, 2.0)
    return net.eval()


def arrays(net: torch.nn.Module) -> dict[str, np.ndarray]:
    return {k: v.detach().numpy().copy() for k, v in net.state_dict().items()}


@pytest.mark.parametrize(
    "config",
    [
        default_model_config(H, 4),  # this project's: BatchNorm, circular, residual
        # The authors' layout: no BatchNorm, zero padding, align_corners, sigmoid.
        {"in_channels": H, "width": 4, "norm": False, "circular": False, "sigmoid": True},
    ],
    ids=["project", "authors"],
)
def test_frozen_unet_computes_torchs_unet(config):
    net = random_net(config, seed=3)
    frozen = FrozenUNet(arrays(net), config)
    bevs = (np.random.default_rng(4).random((3, H, R, S)) < 0.1).astype(np.float32)
    with torch.no_grad():
        ref = net.unet.correction(torch.from_numpy(bevs)).numpy()
    out = frozen.correction(bevs)
    assert out.shape == ref.shape and out.dtype == np.float32
    scale = np.abs(ref).max()
    assert scale > 0.1
    np.testing.assert_allclose(out, ref, atol=1e-5 * max(scale, 1.0))
    # One scan alone gives what it gives in a batch (the padding does not leak).
    np.testing.assert_allclose(frozen.correction(bevs[1:2])[0], out[1], atol=1e-5 * scale)


def test_frozen_model_embeds_and_fingerprints_as_the_torch_model():
    config = default_model_config(H, 4)
    net = random_net(config, seed=5)
    torch_model = DiscoModel(net, BEVConfig(), config, name="t")
    state = arrays(net)
    frozen = DiscoModel(FrozenUNet(state, config), BEVConfig(), config, name="t", state=state)
    assert frozen.fingerprint == torch_model.fingerprint
    bevs = (np.random.default_rng(6).random((2, H, R, S)) < 0.1).astype(np.float32)
    s0, f0 = torch_model.embed(bevs)
    s1, f1 = frozen.embed(bevs)
    assert f1.shape == f0.shape == (2, 2, R, S)
    np.testing.assert_allclose(f1, f0, atol=1e-4)
    np.testing.assert_allclose(s1, s0, atol=1e-5)


def test_a_state_that_does_not_fit_is_refused():
    config = default_model_config(H, 4)
    state = arrays(random_net(config, seed=1))
    wrong = dict(state)
    wrong["unet.dconv_up2.0.conv.weight"] = np.zeros((8, 3, 3, 3), np.float32)
    with pytest.raises(ValueError, match="dconv_up2.0.conv.weight has shape"):
        FrozenUNet(wrong, config)
    missing = {k: v for k, v in state.items() if "dconv_down3.4" not in k}
    with pytest.raises(ValueError, match="missing keys"):
        FrozenUNet(missing, config)


def test_a_config_key_the_network_does_not_know_is_refused(tmp_path):
    config = default_model_config(H, 4)
    state = arrays(random_net(config, seed=1))
    FrozenUNet(state, {**config, "layout": "DiSCO-pytorch"})  # every known key is taken
    with pytest.raises(ValueError, match="unknown keys dropout, widht"):
        FrozenUNet(state, {**config, "widht": 4, "dropout": 0.1})
    # Through the loader: one line naming the file and the key.
    bad = tmp_path / "bad.npz"
    save_npz(bad, state, BEVConfig().to_dict(), {**config, "widht": 4})
    with pytest.raises(ModelError, match="bad.npz: .*unknown keys widht") as err:
        load_model(str(bad))
    assert "\n" not in str(err.value)


def test_npz_weights_load_and_bad_ones_name_the_file(tmp_path):
    config = default_model_config(H, 4)
    net = random_net(config, seed=2)
    path = tmp_path / "w.npz"
    save_npz(path, net.state_dict(), BEVConfig().to_dict(), config, "test")
    model = load_model(str(path))
    assert model.frozen and model.name == "w"
    assert model.fingerprint == DiscoModel(net, BEVConfig(), config).fingerprint

    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(ModelError, match="junk.npz: not a readable .npz"):
        load_model(str(junk))
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, a=np.zeros(3))
    with pytest.raises(ModelError, match="foreign.npz: an .npz without disco weights"):
        load_model(str(foreign))
    state, meta = read_npz(path)
    state.pop("unet.conv_last.bias")
    cut = tmp_path / "cut.npz"
    save_npz(cut, state, meta["bev_config"], meta["model_config"])
    with pytest.raises(ModelError, match="cut.npz: damaged weights"):
        load_model(str(cut))
    # An object array would need pickle: refused without running anything.
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, __disco__=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ModelError, match="pickled.npz"):
        load_model(str(pickled))
    # A truncated zip.
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ModelError, match="truncated.npz"):
        load_model(str(truncated))
    assert zipfile.is_zipfile(path)


@needs_default
def test_shipped_npz_holds_the_shipped_checkpoint():
    ckpt = read_checkpoint(DEFAULT_WEIGHTS)
    state, meta = read_npz(npz_beside(DEFAULT_WEIGHTS))
    assert sorted(state) == sorted(ckpt["state_dict"])
    for key, value in ckpt["state_dict"].items():
        assert state[key].dtype == value.numpy().dtype
        np.testing.assert_array_equal(state[key], value.numpy())
    assert meta["model_config"] == ckpt["model_config"]
    assert meta["bev_config"] == ckpt["bev_config"]
    assert meta["command"] == ckpt["command"]
    assert meta["source_sha256"] == file_sha256(DEFAULT_WEIGHTS)  # else default uses torch


def _torch_default() -> DiscoModel:
    ckpt = read_checkpoint(DEFAULT_WEIGHTS)
    net = build_net(ckpt["model_config"])
    net.load_state_dict(ckpt["state_dict"])
    bev = BEVConfig.from_dict(ckpt["bev_config"])
    return DiscoModel(net, bev, ckpt["model_config"], name="default")


def _scans(folder, n: int) -> list:
    paths = list_scans(folder)
    return [read_scan(p) for p in paths[: min(n, len(paths))]]


def _compare_on(scans: list) -> None:
    frozen, ref = load_model("default"), _torch_default()
    assert frozen.frozen and not ref.frozen
    assert frozen.fingerprint == ref.fingerprint
    bevs = np.stack([polar_bev(p, frozen.bev_config) for p in scans])
    s1, f1 = frozen.embed(bevs)
    s0, f0 = ref.embed(bevs)
    np.testing.assert_allclose(f1, f0, atol=1e-4)
    np.testing.assert_allclose(s1, s0, atol=1e-5)
    # Yaw of every scan against the others, as a query computes it: within 0.01 degree.
    # Rolled copies make sure large turns are among them (the truth: the roll itself).
    for i in range(len(scans)):
        y1 = frozen.yaw(f1[i], f1)
        y0 = ref.yaw(f0[i], f0)
        assert np.abs((y1 - y0 + 180) % 360 - 180).max() < 0.01
        d1, _ = frozen.rerank(f1[i], f1)
        d0, _ = ref.rerank(f0[i], f0)
        np.testing.assert_allclose(d1, d0, atol=1e-5)
    rolled = np.roll(bevs[:1], 30, axis=-1)  # the query turned by -90 degrees
    _, fr = frozen.embed(rolled)
    assert abs(float(frozen.yaw(fr[0], f1[:1])[0]) + 90.0) < 0.01


@needs_default
def test_default_on_the_samples_matches_torch(samples):
    _compare_on(_scans(samples / "00" / "velodyne", 4) + _scans(samples / "01" / "velodyne", 4))


@needs_default
def test_default_on_real_scans_matches_torch(realdata):
    _compare_on(_scans(realdata / "kitti00" / "velodyne", 12))


@needs_default
def test_the_query_path_never_imports_torch(samples, tmp_path):
    """`disco build-db` and `disco query` with the shipped model, in a fresh interpreter:
    the answer comes, and neither torch nor scipy.fft is among the loaded modules."""
    db = tmp_path / "m.db"
    code = (
        "import sys\n"
        "from disco_cli.cli import app\n"
        "for argv in (sys.argv[1:4], sys.argv[4:]):\n"
        "    try:\n"
        "        app(argv)\n"
        "    except SystemExit as e:\n"
        "        assert not e.code, e.code\n"
        "print('TORCH', any(m == 'torch' or m.startswith('torch.') for m in sys.modules))\n"
        "print('SCIPYFFT', 'scipy.fft' in sys.modules)\n"
    )
    args = ["build-db", str(samples / "00"), f"-o{db}"]
    args += ["query", str(samples / "01" / "velodyne" / "000005.bin"), "--db", str(db)]
    args += ["--format", "tsv", "--topk", "1"]
    env = {"PYTHONPATH": package_path(), "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, env=env
    )
    assert out.returncode == 0, out.stderr
    assert "TORCH False" in out.stdout
    assert "SCIPYFFT False" in out.stdout  # model/fft.py loads only SciPy's pocketfft
    assert "000004.bin" in out.stdout  # the right place (README's example)


@needs_default
def test_default_reads_the_pt_when_the_npz_is_of_other_weights(tmp_path, monkeypatch):
    """New default.pt without a new default.npz: the .npz no longer matches the .pt's
    SHA-256, and `default` is the .pt's weights (read with torch), not the stale copy."""
    import shutil

    import disco_cli.model as registry
    from disco_cli.model.checkpoint import save_checkpoint

    ckpt = read_checkpoint(DEFAULT_WEIGHTS)
    ckpt["state_dict"]["unet.conv_last.bias"] = ckpt["state_dict"]["unet.conv_last.bias"] + 1
    ckpt.pop("format")
    pt = tmp_path / "default.pt"
    save_checkpoint(pt, ckpt)
    shutil.copy(npz_beside(DEFAULT_WEIGHTS), npz_beside(pt))
    monkeypatch.setattr(registry, "DEFAULT_WEIGHTS", pt)
    stale = load_model(str(npz_beside(pt)))
    fresh = load_model("default")
    assert fresh.fingerprint != stale.fingerprint
    assert fresh.fingerprint == load_model(str(pt)).fingerprint
    # Made again from the new .pt, the copy is used.
    from disco_cli.model.weights_npz import convert

    convert(pt, npz_beside(pt))
    assert load_model("default").fingerprint == fresh.fingerprint
