"""The model registry, the U-Net's rotation equivariance, signatures, checkpoints."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from disco_cli.errors import ModelError  # noqa: E402
from disco_cli.model import DEFAULT_WEIGHTS, load_model  # noqa: E402
from disco_cli.model.checkpoint import save_checkpoint  # noqa: E402
from disco_cli.model.disco import DiscoModel, build_net, default_model_config  # noqa: E402
from disco_cli.model.signature import signatures, signatures_torch  # noqa: E402

H, R, S = 20, 40, 120


def random_bevs(n: int, seed: int = 0, density: float = 0.08) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.random((n, H, R, S)) < density).astype(np.float32)


def tiny_model(width: int = 4, seed: int = 0) -> DiscoModel:
    from disco_cli.model.bev import BEVConfig

    torch.manual_seed(seed)
    config = default_model_config(H, width)
    net = build_net(config)
    # A last layer and BatchNorm statistics as after training (the residual model starts
    # with a zero last layer, which would leave only the identity path to test).
    torch.nn.init.normal_(net.unet.conv_last.weight, std=0.5)
    for mod in net.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 2.0)
    return DiscoModel(net, BEVConfig(), config, name="tiny")


def test_spectral_model_follows_the_protocol():
    model = load_model("spectral")
    assert model.name == "spectral" and model.query_policy.rerank_candidates == 0
    assert len(model.fingerprint) >= 8
    json.dumps(model.config_dict())  # stored inside databases: must be plain JSON
    bevs = random_bevs(3)
    sigs, feats = model.embed(bevs)
    assert sigs.dtype == np.float32 and feats.dtype == np.float32
    assert sigs.shape == (3, 32 * 32) and feats.shape == (3, R, S)
    np.testing.assert_allclose(np.linalg.norm(sigs, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(feats, bevs.sum(axis=1))
    assert load_model("spectral").fingerprint == model.fingerprint


def test_signature_matches_a_numpy_reference():
    rng = np.random.default_rng(1)
    g = rng.random((2, R, S)).astype(np.float32)
    # Reference: float64 |FFT2|, zero frequency moved to (R//2, S//2), 32 x 32 around it.
    spec = np.abs(np.fft.fftshift(np.fft.fft2(g.astype(np.float64)), axes=(1, 2)))
    crop = spec[:, R // 2 - 16 : R // 2 + 16, S // 2 - 16 : S // 2 + 16].reshape(2, -1)
    ref = crop / np.linalg.norm(crop, axis=1, keepdims=True)
    np.testing.assert_allclose(signatures(g), ref, atol=1e-5)
    np.testing.assert_allclose(signatures_torch(torch.from_numpy(g)).numpy(), ref, atol=1e-5)
    assert signatures(g, crop=(8, 16)).shape == (2, 128)


@pytest.mark.parametrize("shift", [8, 16, 64, 112])
def test_unet_signature_is_exactly_invariant_to_rolls_by_the_stride(shift):
    model = tiny_model()
    bevs = random_bevs(2, seed=2)
    sig, feat = model.embed(bevs)
    sig_r, feat_r = model.embed(np.roll(bevs, shift, axis=-1))
    # The feature image rolls with the input across the 0/360 seam...
    np.testing.assert_allclose(feat_r, np.roll(feat, shift, axis=-1), atol=1e-4)
    # ...so its spectrum magnitude does not change.
    np.testing.assert_allclose(sig_r, sig, atol=1e-5)


@pytest.mark.parametrize("shift", [1, 3, 13, 59])
def test_unet_signature_is_nearly_invariant_to_other_rolls(shift):
    model = tiny_model()
    bevs = random_bevs(4, seed=3)
    sig, _ = model.embed(bevs)
    sig_r, _ = model.embed(np.roll(bevs, shift, axis=-1))
    other, _ = model.embed(random_bevs(4, seed=4))
    same = np.linalg.norm(sig_r - sig, axis=1)
    different = np.linalg.norm(other - sig, axis=1)
    assert same.max() < 0.05
    assert same.max() < 0.2 * different.min()


def test_checkpoint_round_trip_with_weights_only(tmp_path):
    model = tiny_model(seed=5)
    path = tmp_path / "m.pt"
    save_checkpoint(
        path,
        {
            "state_dict": model.net.state_dict(),
            "bev_config": model.bev_config.to_dict(),
            "model_config": model.model_config,
            "command": "disco train x -o m.pt",
        },
    )
    raw = torch.load(path, weights_only=True)
    assert raw["command"] == "disco train x -o m.pt"
    loaded = load_model(str(path))
    assert loaded.fingerprint == model.fingerprint
    assert loaded.config_dict()["model_config"] == model.model_config
    bevs = random_bevs(3, seed=6)
    np.testing.assert_allclose(loaded.embed(bevs)[1], model.embed(bevs)[1], atol=1e-6)


def test_missing_corrupt_and_foreign_checkpoints_raise_model_error(tmp_path):
    with pytest.raises(ModelError, match="nope.pt"):
        load_model(tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"this is not a checkpoint")
    with pytest.raises(ModelError, match="bad.pt"):
        load_model(str(bad))
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ModelError, match="foreign.pt: not a disco checkpoint .unknown layout"):
        load_model(str(foreign))
    damaged = tmp_path / "damaged.pt"
    model = tiny_model()
    sd = model.net.state_dict()
    sd.pop("unet.conv_last.weight")
    save_checkpoint(
        damaged,
        {
            "state_dict": sd,
            "bev_config": model.bev_config.to_dict(),
            "model_config": model.model_config,
            "command": "",
        },
    )
    with pytest.raises(ModelError, match="damaged.pt"):
        load_model(str(damaged))


class _Evil:
    """Unpickling this would create a file: weights_only loading must refuse it."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_pickled_object_is_refused_not_executed(tmp_path):
    evil = tmp_path / "evil.pt"
    marker = tmp_path / "marker"
    torch.save({"format": "disco-cli/1", "payload": _Evil(str(marker))}, evil)
    with pytest.raises(ModelError, match="evil.pt: not a disco checkpoint") as refused:
        load_model(str(evil))
    assert not marker.exists()
    # Never the advice to load it unsafely (torch's own message gives it).
    assert "weights_only" not in str(refused.value)


# -- the authors' DiSCO-pytorch layout ------------------------------------------------

AUTHORS_BLOCKS = {
    "dconv_down1": (H, 64),
    "dconv_down2": (64, 128),
    "dconv_down3": (128, 256),
    "dconv_down4": (256, 512),
    "dconv_up3": (512 + 256, 256),
    "dconv_up2": (256 + 128, 128),
    "dconv_up1": (128 + 64, 64),
}


def authors_state_dict(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state_dict in the layout we assume for the authors' release (docs/model.md)."""
    g = torch.Generator().manual_seed(seed)
    sd: dict[str, torch.Tensor] = {}
    for name, (cin, cout) in AUTHORS_BLOCKS.items():
        for idx, c_in in ((0, cin), (2, cout)):
            scale = (2.0 / (9 * c_in)) ** 0.5
            sd[f"unet.{name}.{idx}.weight"] = torch.randn(cout, c_in, 3, 3, generator=g) * scale
            sd[f"unet.{name}.{idx}.bias"] = torch.randn(cout, generator=g) * 0.01
    sd["unet.conv_last.weight"] = torch.randn(1, 64, 1, 1, generator=g) * 0.1
    sd["unet.conv_last.bias"] = torch.zeros(1)
    sd["corr2soft.softmax_w"] = torch.tensor([5.0])
    sd["corr2soft.softmax_b"] = torch.tensor([0.1])
    return sd


def authors_forward(sd: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Reference forward of that layout, written from the layout alone: zero-padded 3x3
    double convs with ReLU, 2x max-pool, bilinear 2x upsampling (align_corners=True),
    skip concatenation, 1x1 conv, Sigmoid."""
    from torch.nn import functional as F

    def block(name: str, t: torch.Tensor) -> torch.Tensor:
        for idx in (0, 2):
            t = F.relu(
                F.conv2d(
                    t, sd[f"unet.{name}.{idx}.weight"], sd[f"unet.{name}.{idx}.bias"], padding=1
                )
            )
        return t

    def up(t: torch.Tensor) -> torch.Tensor:
        return F.interpolate(t, scale_factor=2, mode="bilinear", align_corners=True)

    c1 = block("dconv_down1", x)
    c2 = block("dconv_down2", F.max_pool2d(c1, 2))
    c3 = block("dconv_down3", F.max_pool2d(c2, 2))
    t = block("dconv_down4", F.max_pool2d(c3, 2))
    t = block("dconv_up3", torch.cat([up(t), c3], 1))
    t = block("dconv_up2", torch.cat([up(t), c2], 1))
    t = block("dconv_up1", torch.cat([up(t), c1], 1))
    return torch.sigmoid(F.conv2d(t, sd["unet.conv_last.weight"], sd["unet.conv_last.bias"]))[:, 0]


def test_authors_layout_loads_and_computes_their_network(tmp_path):
    sd = authors_state_dict()
    path = tmp_path / "nclt_disco.pth"
    torch.save({"state_dict": sd, "epoch": 30}, path)
    model = load_model(str(path))
    assert model.model_config["width"] == 64 and model.model_config["in_channels"] == H
    cfg = model.bev_config
    assert (cfg.heights, cfg.rings, cfg.sectors, cfg.max_range) == (20, 40, 120, 80.0)
    assert float(model.net.corr2soft.softmax_w.detach()) == 5.0
    bevs = random_bevs(2, seed=8)
    with torch.no_grad():
        ref = authors_forward(sd, torch.from_numpy(bevs)).numpy()
    _, feats = model.embed(bevs)
    np.testing.assert_allclose(feats, ref, atol=1e-5)


def test_authors_layout_with_a_missing_block_is_refused(tmp_path):
    sd = authors_state_dict()
    del sd["unet.dconv_up2.2.weight"]
    path = tmp_path / "broken.pth"
    torch.save({"state_dict": sd}, path)
    with pytest.raises(ModelError, match="broken.pth"):
        load_model(str(path))


def test_scancontext_name_maps_to_its_model():
    model = load_model("scancontext")
    assert type(model).__name__ == "ScanContextModel"
    assert model.query_policy.rerank_candidates > 0


def test_default_without_shipped_weights_says_so(tmp_path, monkeypatch):
    import disco_cli.model as registry

    monkeypatch.setattr(registry, "DEFAULT_WEIGHTS", tmp_path / "absent.pt")
    with pytest.raises(ModelError, match="absent.pt: no shipped weights yet"):
        load_model("default")


@pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="no shipped weights")
def test_shipped_weights_are_small_self_describing_and_invariant():
    raw = torch.load(DEFAULT_WEIGHTS, weights_only=True)
    assert DEFAULT_WEIGHTS.stat().st_size < 5_000_000
    assert raw["command"].startswith("disco train") and "train_state" not in raw
    model = load_model("default")
    assert (
        model.name == "default"
        and model.fingerprint == load_model(str(DEFAULT_WEIGHTS)).fingerprint
    )
    bevs = random_bevs(2, seed=9)
    sig, _ = model.embed(bevs)
    np.testing.assert_allclose(model.embed(np.roll(bevs, 40, axis=-1))[0], sig, atol=1e-5)


@pytest.mark.parametrize("name", ["spectral", "tiny"])
def test_empty_batches_and_empty_scans(name):
    model = tiny_model() if name == "tiny" else load_model(name)
    # The residual network keeps two images per scan (G, U), spectral one.
    fshape = (2, R, S) if name == "tiny" else (R, S)
    sigs, feats = model.embed(np.zeros((0, H, R, S), np.float32))
    assert sigs.shape == (0, 1024) and feats.shape == (0, *fshape)
    empty = np.zeros((0, *fshape), np.float32)
    assert model.yaw(np.zeros(fshape, np.float32), empty).shape == (0,)
    # An empty scan (all cells empty) gives finite numbers, not NaN from 0 / 0.
    sigs, feats = model.embed(np.zeros((2, H, R, S), np.float32))
    assert np.isfinite(sigs).all() and np.isfinite(model.yaw(feats[0], feats)).all()
    with pytest.raises(ValueError):
        model.embed(np.zeros((2, R, S), np.float32))


def test_a_bev_of_another_configuration_is_a_model_error():
    with pytest.raises(ModelError, match="expects 20 BEV heights, got 10"):
        tiny_model().embed(np.zeros((1, 10, R, S), np.float32))
