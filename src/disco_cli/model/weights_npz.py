"""Model weights as a NumPy `.npz` file, which loads without torch.

A `disco-cli/1` checkpoint (`checkpoint.py`) needs torch to read, and importing torch
takes about a second: most of a one-scan `disco query`. The same weights in an `.npz`
load in milliseconds and run on `unet_numpy.FrozenUNet`. The file holds the state
dict's arrays under their own names, unchanged (so the model's fingerprint is the
same as the checkpoint's), and one string array `__disco__`: JSON with the format,
`bev_config`, `model_config` and the source checkpoint's `command`. It is read with
`allow_pickle=False`, so an untrusted file cannot run code. A conversion also records
the SHA-256 of the checkpoint it came from (`source_sha256`): `default` loads its
`.npz` only while that still matches `default.pt`.

    python -m disco_cli.model.weights_npz CHECKPOINT.pt OUT.npz

made `weights/default.npz` from `weights/default.pt` (tests/test_model_numpy.py checks
that the two agree).
"""

from __future__ import annotations

import hashlib
import json
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import ModelError
from disco_cli.io.output_paths import atomic_path
from disco_cli.model.disco import to_numpy

FORMAT = "disco-cli-npz/1"
_META = "__disco__"


def save_npz(
    path: str | Path,
    state: dict[str, Any],
    bev_config: dict[str, Any],
    model_config: dict[str, Any],
    command: str = "",
    source_sha256: str = "",
) -> None:
    """Write weights atomically (arrays, or torch tensors converted as they are)."""
    path = Path(path)
    meta = {
        "format": FORMAT,
        "bev_config": dict(bev_config),
        "model_config": dict(model_config),
        "command": str(command),
        "source_sha256": str(source_sha256),
    }
    arrays = {key: to_numpy(value) for key, value in state.items()}
    if _META in arrays:
        raise ValueError(f"a state dict key may not be {_META}")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays, **{_META: np.array(json.dumps(meta, sort_keys=True))})


def read_npz(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(state arrays, meta dict) of an `.npz` weights file; ModelError naming the file
    when it is missing, not an npz, or not this format."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such model file (names: default, spectral, scancontext)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {key: z[key] for key in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{path}: not a readable .npz weights file ({reason[:200]})") from None
    raw = arrays.pop(_META, None)
    try:
        meta = json.loads(str(raw)) if raw is not None and raw.ndim == 0 else None
    except ValueError:
        meta = None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelError(f"{path}: an .npz without disco weights ({_META} missing or foreign)")
    return arrays, meta


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def convert(src: str | Path, dst: str | Path) -> None:
    """An `.npz` of a `disco-cli/1` checkpoint (needs torch)."""
    # deferred: torch (~1.5 s) reads checkpoints; this module is on the query path
    from disco_cli.model.checkpoint import FORMAT as CKPT_FORMAT
    from disco_cli.model.checkpoint import read_checkpoint

    ckpt = read_checkpoint(src)
    if ckpt.get("format") != CKPT_FORMAT:
        raise ModelError(f"{src}: not a {CKPT_FORMAT} checkpoint")
    save_npz(
        dst,
        ckpt["state_dict"],
        dict(ckpt["bev_config"]),
        dict(ckpt["model_config"]),
        str(ckpt.get("command", "")),
        file_sha256(src),
    )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m disco_cli.model.weights_npz CHECKPOINT.pt OUT.npz")
    try:
        convert(sys.argv[1], sys.argv[2])
    except ModelError as exc:
        sys.exit(str(exc))
