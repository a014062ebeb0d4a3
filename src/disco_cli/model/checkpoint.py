"""Checkpoints: plain dicts of tensors, numbers and strings that load with weights_only=True.

Layout (`format` = "disco-cli/1"):
    state_dict     the DiscoNet weights (U-Net and the yaw softmax)
    bev_config     BEVConfig.to_dict()
    model_config   {"in_channels", "width", "norm", "circular", "sigmoid", "crop"}
    command        the training command line, as a string
    train_state    optional: epoch, step, optimizer and RNG state (for `--resume`)
    metrics        optional: validation figures at save time
Configs are stored as plain dicts, never dataclasses, so that loading an untrusted file
cannot run code.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch

from disco_cli.errors import ModelError
from disco_cli.io.output_paths import atomic_path

FORMAT = "disco-cli/1"


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write a checkpoint atomically (a crash mid-write leaves the old file intact, and
    no temporary file); its folder must exist."""
    with atomic_path(path) as tmp:
        torch.save({"format": FORMAT, **payload}, tmp)


def read_checkpoint(path: str | Path, device: str = "cpu") -> dict[str, Any]:
    """The raw checkpoint dict; ModelError naming the file when it is missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such model file (names: default, spectral, scancontext)")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols it meets
            warnings.simplefilter("ignore")
            ckpt = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises many kinds for a corrupt or foreign file
        raise ModelError(f"{path}: not a disco checkpoint ({_why_unreadable(exc)})") from None
    if not isinstance(ckpt, dict):
        raise ModelError(f"{path}: not a disco checkpoint (holds a {type(ckpt).__name__})")
    return ckpt


def _why_unreadable(exc: Exception) -> str:
    """Why torch could not load a file, in a few words. Torch's own message would
    advise weights_only=False, which runs whatever code the file holds: not for a
    file that is not a disco checkpoint."""
    text = str(exc)
    if "weights only" in text.lower() or "weights_only" in text:
        return "it holds Python objects, not only tensors, numbers and strings"
    if isinstance(exc, EOFError) or not text.strip():
        return "empty or cut short"
    return "not a PyTorch file"


def export_checkpoint(
    src: str | Path, dst: str | Path, notes: dict[str, Any] | None = None
) -> None:
    """A copy of a training checkpoint for shipping: without the optimizer state (which
    doubles the size), with `notes` (e.g. validation figures) added under `metrics`."""
    ckpt = read_checkpoint(src)
    ckpt.pop("train_state", None)
    ckpt.pop("format", None)
    if notes:
        ckpt["metrics"] = {**dict(ckpt.get("metrics", {})), **notes}
    save_checkpoint(dst, ckpt)
