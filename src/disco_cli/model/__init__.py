"""The DiSCO network, signatures, yaw, checkpoints and the model registry.

`load_model(name_or_path)` returns a `model.interface.QueryModel`: `name`, `bev_config`,
`fingerprint`, `config_dict()`, `embed(bevs) -> (signatures, features)`, the yaw,
re-ranking and position hooks of the query stage, `abilities` (which of those it has)
and `query_policy` (the settings it was tuned with).

Names: `default` (the shipped weights), `spectral` (training-free, no torch needed),
`scancontext` (the Scan Context baseline); anything else is a checkpoint path, in this
project's layout or in the layout of the authors' DiSCO-pytorch release, or an `.npz`
of weights (`weights_npz.py`).

On the CPU a model of this project's layout runs its U-Net in NumPy (`unet_numpy.py`);
`default` and `.npz` weights then never import torch, which is most of the time a
one-scan `disco query` takes.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from disco_cli.errors import DiscoError, ModelError
from disco_cli.runtime.threads import ensure_threads

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.pt"


def npz_beside(checkpoint: Path) -> Path:
    """The torch-free copy of a checkpoint's weights (`weights_npz.py`), where shipped."""
    return checkpoint.with_suffix(".npz")


def _spectral(device: str) -> Any:
    # deferred: a model's code loads when it is chosen (and model.* modules import this one)
    from disco_cli.model.spectral import SpectralModel

    return SpectralModel()


def _scancontext(device: str) -> Any:
    module = importlib.import_module("disco_cli.model.scancontext")
    return module.ScanContextModel()


def _default(device: str) -> Any:
    if not DEFAULT_WEIGHTS.is_file():
        raise ModelError(f"{DEFAULT_WEIGHTS}: no shipped weights yet; use --model spectral")
    if device == "cpu" and npz_beside(DEFAULT_WEIGHTS).is_file():
        # deferred: as in _spectral; weights_npz imports this package (through model.disco)
        from disco_cli.model.weights_npz import file_sha256, read_npz

        npz = npz_beside(DEFAULT_WEIGHTS)
        state, meta = read_npz(npz)
        # Only a copy of these very weights: new default.pt without a new .npz -> torch.
        if meta.get("source_sha256") == file_sha256(DEFAULT_WEIGHTS):
            bev, cfg = meta.get("bev_config"), meta.get("model_config")
            return _frozen_model(state, bev, cfg, npz, "default")
    return load_checkpoint_model(DEFAULT_WEIGHTS, device=device, name="default")


# The model registry: name -> factory(device). A checkpoint path is the fallback.
MODELS: dict[str, Callable[[str], Any]] = {
    "default": _default,
    "spectral": _spectral,
    "scancontext": _scancontext,
}


def check_device(device: str) -> None:
    """`DiscoError` unless `device` is cpu, or cuda with a CUDA device that torch sees."""
    if device not in ("cpu", "cuda"):
        raise DiscoError(f"--device must be cpu or cuda, not {device!r}")
    if device == "cuda":
        import torch  # deferred: torch costs ~1.5 s; only --device cuda asks it

        if not torch.cuda.is_available():
            raise DiscoError("--device cuda: torch sees no CUDA device here; use --device cpu")


def load_model(name_or_path: str | Path = "default", device: str = "cpu") -> Any:
    """A model by registry name or checkpoint path; ModelError naming the file on failure."""
    ensure_threads()  # before the model's first torch op
    key = str(name_or_path)
    if key in MODELS:
        return MODELS[key](device)
    if Path(key).suffix == ".npz" and device == "cpu":
        return load_npz_model(Path(key))
    return load_checkpoint_model(Path(key), device=device)


def load_npz_model(path: str | Path, name: str | None = None) -> Any:
    """A DiscoModel on the CPU from an `.npz` of weights, without torch."""
    from disco_cli.model.weights_npz import read_npz  # deferred: as in _default

    path = Path(path)
    state, meta = read_npz(path)
    return _frozen_model(state, meta.get("bev_config"), meta.get("model_config"), path, name)


def _frozen_model(state: Any, bev: Any, model_config: Any, path: Path, name: str | None) -> Any:
    # deferred: the registry loads no model code (nor numpy) until a model is chosen, and
    # model.disco imports this package
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.disco import DiscoModel, to_numpy
    from disco_cli.model.unet_numpy import FrozenUNet

    try:
        arrays = {str(k): to_numpy(v) for k, v in dict(state).items()}
        model_config = dict(model_config)
        bev_config = BEVConfig.from_dict(dict(bev))
        net = FrozenUNet(arrays, model_config)
    except (KeyError, TypeError, ValueError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{path}: damaged weights ({reason[:200]})") from None
    name = name or Path(path).stem
    return DiscoModel(net, bev_config, model_config, name=name, state=arrays)


def load_checkpoint_model(path: str | Path, device: str = "cpu", name: str | None = None) -> Any:
    """A DiscoModel from a checkpoint file of either supported layout."""
    # deferred: torch (~1.5 s) and the checkpoint readers load only for a checkpoint
    from disco_cli.model.authors import is_authors_checkpoint, model_from_authors
    from disco_cli.model.checkpoint import FORMAT, read_checkpoint

    path = Path(path)
    ckpt = read_checkpoint(path, device="cpu")
    if ckpt.get("format") == FORMAT:
        return model_from_checkpoint(ckpt, path, device=device, name=name)
    if is_authors_checkpoint(ckpt):
        return model_from_authors(ckpt, path, device=device, name=name)
    keys = ", ".join(sorted(map(str, ckpt))[:5])
    raise ModelError(f"{path}: not a disco checkpoint (unknown layout; top-level keys: {keys})")


def model_from_checkpoint(
    ckpt: dict[str, Any], path: str | Path, device: str = "cpu", name: str | None = None
) -> Any:
    # deferred: as in _frozen_model
    from disco_cli.model.bev import BEVConfig
    from disco_cli.model.disco import DiscoModel, build_net

    if device == "cpu":
        # torch read the file; the NumPy U-Net runs it (the same features, faster).
        state = ckpt.get("state_dict")
        return _frozen_model(state, ckpt.get("bev_config"), ckpt.get("model_config"), path, name)
    try:
        model_config = dict(ckpt["model_config"])
        bev_config = BEVConfig.from_dict(dict(ckpt["bev_config"]))
        net = build_net(model_config)
        net.load_state_dict(ckpt["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{path}: damaged checkpoint ({reason[:200]})") from None
    return DiscoModel(net, bev_config, model_config, name=name or Path(path).stem, device=device)


__all__ = [
    "MODELS",
    "DEFAULT_WEIGHTS",
    "check_device",
    "load_model",
    "load_checkpoint_model",
    "load_npz_model",
]
