"""Loading a checkpoint in the layout of the authors' DiSCO-pytorch release (NCLT model).

Assumed layout (we do not have the file; docs/model.md describes it): a dict with a
`state_dict` whose keys are
    unet.dconv_down{1..4}.{0,2}.{weight,bias}   double 3x3 conv blocks (conv, ReLU, conv, ReLU)
    unet.dconv_up{3,2,1}.{0,2}.{weight,bias}
    unet.conv_last.{weight,bias}                 1x1 conv to one channel (or conv_last.0.*)
    corr2soft.softmax_w, corr2soft.softmax_b     the yaw softmax parameters
with a 64-channel base, zero padding, bilinear upsampling (align_corners=True) and a final
Sigmoid. It maps onto our UNet with norm=False, circular=False, sigmoid=True; the BEV is
the paper's NCLT preprocessing (see `authors_bev_config`).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from disco_cli.errors import ModelError
from disco_cli.model.bev import BEVConfig
from disco_cli.model.disco import DiscoModel, build_net
from disco_cli.model.signature import DEFAULT_CROP

_BLOCK = re.compile(r"^unet\.(dconv_(?:down[1-4]|up[1-3]))\.([02])\.(weight|bias)$")
_LAST = re.compile(r"^unet\.conv_last(?:\.0)?\.(weight|bias)$")


def is_authors_checkpoint(ckpt: dict[str, Any]) -> bool:
    sd = ckpt.get("state_dict")
    return isinstance(sd, dict) and any(str(k).startswith("unet.dconv_down1.") for k in sd)


def authors_bev_config() -> Any:
    """The paper's NCLT BEV: 20 heights x 40 rings x 120 sectors, occupancy, 80 m range."""
    return BEVConfig.from_dict(AUTHORS_BEV)


# The paper: points within 80 m and 20 m of height, ground removed, 40 x 120 x 20 occupancy.
AUTHORS_BEV: dict[str, Any] = {
    "rings": 40,
    "sectors": 120,
    "heights": 20,
    "max_range": 80.0,
    "min_range": 3.0,
    "z_min": -1.5,  # about the ground for a roof-mounted sensor: the area filter's stand-in
    "z_max": 18.5,
    "mode": "occupancy",
}


def convert_state_dict(sd: dict[str, Any]) -> dict[str, Any]:
    """The authors' keys renamed to ours; ModelError-free (the caller checks completeness)."""
    out: dict[str, Any] = {}
    for key, value in sd.items():
        key = str(key)
        if m := _BLOCK.match(key):
            # Our PolarConv wraps the Conv2d as `.conv`; the Sequential indices are the same.
            out[f"unet.{m[1]}.{m[2]}.conv.{m[3]}"] = value
        elif m := _LAST.match(key):
            out[f"unet.conv_last.{m[1]}"] = value
        elif key in ("corr2soft.softmax_w", "corr2soft.softmax_b"):
            out[key] = value.reshape(1).float()
    return out


def model_from_authors(
    ckpt: dict[str, Any], path: str | Path, device: str = "cpu", name: str | None = None
) -> Any:
    sd = convert_state_dict(ckpt["state_dict"])
    first = sd.get("unet.dconv_down1.0.conv.weight")
    if first is None or first.ndim != 4:
        raise ModelError(f"{path}: authors' layout without unet.dconv_down1.0.weight")
    model_config = {
        "in_channels": int(first.shape[1]),
        "width": int(first.shape[0]),
        "norm": False,
        "circular": False,
        "sigmoid": True,
        "residual": False,
        "crop": list(DEFAULT_CROP),
        "layout": "DiSCO-pytorch",
    }
    net = build_net(model_config)
    if "corr2soft.softmax_w" not in sd:  # the softmax is only used in training
        own = net.state_dict()
        sd["corr2soft.softmax_w"] = own["corr2soft.softmax_w"]
        sd["corr2soft.softmax_b"] = own["corr2soft.softmax_b"]
    try:
        net.load_state_dict(sd, strict=True)
    except RuntimeError as exc:
        first_line = str(exc).strip().splitlines()
        detail = " ".join(first_line)[:300]
        raise ModelError(f"{path}: authors' layout does not fit: {detail}") from None
    return DiscoModel(
        net, authors_bev_config(), model_config, name=name or f"{Path(path).stem}", device=device
    )
