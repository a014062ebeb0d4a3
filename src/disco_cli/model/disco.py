"""A learned DiSCO model: the U-Net F_cnn in torch or NumPy, signatures and yaw in NumPy.

A model loaded for inference on the CPU runs the U-Net in NumPy (`unet_numpy.FrozenUNet`):
the same output within float32 rounding, faster, and without importing torch where the
weights come from a `.npz` file (the shipped `default` does). Training, CUDA and the
models built from a torch network run the torch network.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np

from disco_cli.errors import ModelError
from disco_cli.model.interface import Abilities
from disco_cli.model.signature import DEFAULT_CROP, signatures
from disco_cli.model.unet_numpy import FrozenUNet
from disco_cli.model.verify import aligned_correlation, aligned_correlations
from disco_cli.model.yaw import estimate_yaw, estimate_yaw_conf
from disco_cli.model.yaw_refine import (
    CHECK_BELOW,
    query_in_match_frame_conf,
    recentre_kept,
    refine_yaw_conf,
)
from disco_cli.query.query_policy import QueryPolicy
from disco_cli.runtime.blas_threads import blas_threads
from disco_cli.runtime.threads import get_threads

# Scans per forward pass at inference: large enough to amortize, small enough for memory.
_BATCH = 64
# The NumPy U-Net's activations of 4 scans stay in cache: 4.8 ms per scan against 9.6
# in batches of 64 (and a sixteenth of the memory), minimum of 12 batches at load 11.
_FROZEN_BATCH = 4


def default_model_config(in_channels: int, width: int = 16) -> dict[str, Any]:
    return {
        "in_channels": int(in_channels),
        "width": int(width),
        "norm": True,
        "circular": True,
        "sigmoid": False,
        "residual": True,
        "crop": list(DEFAULT_CROP),
    }


def build_net(model_config: dict[str, Any]) -> Any:
    """The torch DiscoNet of a model configuration."""
    from disco_cli.model.unet import DiscoNet  # deferred: imports torch (0.5 s and more)

    return DiscoNet(
        in_channels=int(model_config["in_channels"]),
        width=int(model_config["width"]),
        norm=bool(model_config.get("norm", True)),
        circular=bool(model_config.get("circular", True)),
        sigmoid=bool(model_config.get("sigmoid", False)),
        residual=bool(model_config.get("residual", False)),
    )


def weights_hash(state_dict: dict[str, Any], config: dict[str, Any]) -> str:
    """Fingerprint of weights (torch tensors or NumPy arrays: the same for both)."""
    h = hashlib.sha256(json.dumps(config, sort_keys=True).encode())
    for key in sorted(state_dict):
        h.update(key.encode())
        h.update(to_numpy(state_dict[key]).tobytes())
    return h.hexdigest()[:16]


def to_numpy(value: Any) -> np.ndarray:
    """A weight as a contiguous NumPy array (a torch tensor is copied off its device)."""
    if hasattr(value, "detach"):  # a torch tensor
        value = value.detach().cpu().contiguous().numpy()
    value = np.asarray(value)  # (np.ascontiguousarray would make a 0-d array 1-d)
    return value if value.flags.c_contiguous else value.copy(order="C")


class DiscoModel:
    """`model.interface.QueryModel` over a DiscoNet: it does everything the query stage
    can ask, with the settings it was tuned with (`QueryPolicy`'s defaults).

    Features: a residual network keeps two images per scan, [2, R, S]: F_cnn's output G
    (signature and yaw) and the U-Net's learned correction U (re-ranking, see verify.py);
    other networks keep G alone, [R, S], and re-rank with it.

    `net` is a torch DiscoNet, or a `FrozenUNet` with `state` (the state dict as NumPy
    arrays, which the fingerprint is taken of).
    """

    abilities = Abilities(rerank=True, refine_yaw=True, locate=True, query_views=True)
    query_policy = QueryPolicy()

    def __init__(
        self,
        net: Any,
        bev_config: Any,
        model_config: dict[str, Any],
        name: str = "disco",
        device: str = "cpu",
        state: dict[str, np.ndarray] | None = None,
    ):
        self.frozen = isinstance(net, FrozenUNet)
        if self.frozen and state is None:
            raise ValueError("a FrozenUNet model needs the state dict it was made from")
        self.net = net if self.frozen else net.to(device).eval()
        self.device = device
        self.bev_config = bev_config
        self.model_config = dict(model_config)
        self.crop = tuple(int(c) for c in self.model_config.get("crop", DEFAULT_CROP))
        self.name = name
        self.two_channel = bool(self.model_config.get("residual", False))
        # The name is left out: the same weights loaded as `default` or by path are one model.
        config = {k: v for k, v in self.config_dict().items() if k != "model"}
        self.fingerprint = weights_hash(state if self.frozen else self.net.state_dict(), config)

    def config_dict(self) -> dict[str, Any]:
        return {
            "model": self.name,
            "kind": "disco",
            "model_config": self.model_config,
            "bev_config": self.bev_config.to_dict(),
            # The stored feature layout; a database built with another one must not match.
            "features": "G,U" if self.two_channel else "G",
        }

    def features(self, bevs: np.ndarray) -> np.ndarray:
        b = np.asarray(bevs, dtype=np.float32)
        if b.ndim != 4:
            raise ValueError(f"bevs must be [B, H, R, S], got shape {b.shape}")
        if b.shape[1:2] != (self.model_config["in_channels"],):
            # A BEV made with another configuration than the model's: the user's mix-up.
            raise ModelError(
                f"model {self.name} expects {self.model_config['in_channels']} BEV heights, "
                f"got {b.shape[1]} (was the BEV made with this model's bev_config?)"
            )
        out = []
        for i in range(0, len(b), _BATCH):
            out.append(self._forward(b[i : i + _BATCH]))
        if not out:
            shape = ((2,) if self.two_channel else ()) + b.shape[2:]
            return np.zeros((0, *shape), np.float32)
        return np.concatenate(out)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        """Features of one batch of BEVs [B, H, R, S]."""
        if self.frozen:
            with blas_threads(get_threads()):
                u = np.concatenate(
                    [
                        self.net.correction(x[i : i + _FROZEN_BATCH])
                        for i in range(0, len(x), _FROZEN_BATCH)
                    ]
                )
            if self.two_channel:
                return np.stack([u + x.sum(axis=1), u], axis=1)
            return u
        import torch  # deferred: only a torch model gets here; CPU queries never load it

        with torch.no_grad():
            t = torch.from_numpy(x).to(self.device)
            if self.two_channel:
                u = self.net.unet.correction(t)
                f = torch.stack([u + t.sum(dim=1), u], dim=1)
            else:
                f = self.net(t)
            return f.float().cpu().numpy()

    def _g(self, features: np.ndarray) -> np.ndarray:
        """F_cnn's output G of features [..., (2,) R, S]."""
        f = np.asarray(features)
        return f[..., 0, :, :] if self.two_channel else f

    def _u(self, features: np.ndarray) -> np.ndarray:
        """The image that re-ranking compares: U for a residual network, else G."""
        f = np.asarray(features)
        return f[..., 1, :, :] if self.two_channel else f

    def embed(self, bevs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        feats = self.features(bevs)
        return signatures(self._g(feats), self.crop), feats

    def yaw(self, query_features: np.ndarray, match_features: np.ndarray) -> np.ndarray:
        return estimate_yaw(self._g(query_features), self._g(match_features))

    def refine_yaw(self, query_features: np.ndarray, match_features: np.ndarray) -> np.ndarray:
        """`yaw` with the parallax of the two sensors' offset removed (yaw_refine.py).

        A residual network's G - U is the BEV summed over heights: its sharp edges
        resample better than the learned G (mean error 0.11 against 0.22 degrees on the
        terrace hard set, docs/research/model-history.md), so that image is re-centred when
        there is one."""
        return self.refine_yaw_conf(query_features, match_features)[0]

    def query_position(
        self, query_features: np.ndarray, match_features: np.ndarray
    ) -> tuple[float, np.ndarray]:
        """(yaw_deg, position [2] of the query sensor in the match's frame, m) of one
        match, parallax-free (`refine_yaw`'s yaw for that match)."""
        yaw, position, _ = self.query_position_conf(query_features, match_features)
        return yaw, position

    def yaw_conf(
        self, query_features: np.ndarray, match_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(`yaw`, its confidence [K] in [0, 1]: yaw.estimate_yaw_conf)."""
        return estimate_yaw_conf(self._g(query_features), self._g(match_features))

    def refine_yaw_conf(
        self,
        query_features: np.ndarray,
        match_features: np.ndarray,
        check_below: float = CHECK_BELOW,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(`refine_yaw`, its confidence [K] in [0, 1]: yaw_refine.refine_checked, the
        second heading checked below `check_below`)."""
        return refine_yaw_conf(
            self.refine_image(query_features),
            self.refine_image(match_features),
            self.bev_config.max_range,
            check_below,
        )

    def query_position_conf(
        self,
        query_features: np.ndarray,
        match_features: np.ndarray,
        check_below: float = CHECK_BELOW,
    ) -> tuple[float, np.ndarray, float]:
        """`query_position` and the yaw's confidence."""
        return query_in_match_frame_conf(
            self.refine_image(query_features),
            self.refine_image(match_features),
            self.bev_config.max_range,
            check_below,
        )

    def refine_image(self, features: np.ndarray) -> np.ndarray:
        """The image that `refine_yaw` re-centres: G - U for a residual network, else G."""
        f = np.asarray(features, dtype=np.float32)
        return f[..., 0, :, :] - f[..., 1, :, :] if self.two_channel else f

    def rerank(
        self, query_features: np.ndarray, candidate_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(distances [K] = 1 - aligned correlation, in [0, 2]; yaw_deg [K]) of candidates."""
        cands = np.asarray(candidate_features)
        if len(cands) == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.float32)
        return self.rerank_distances(query_features, cands), self.yaw(query_features, cands)

    def rerank_distances(
        self, query_features: np.ndarray, candidate_features: np.ndarray
    ) -> np.ndarray:
        """`rerank`'s distances alone (search works out the yaw of the rows it keeps)."""
        cands = np.asarray(candidate_features)
        if len(cands) == 0:
            return np.zeros(0, np.float32)
        score = aligned_correlation(self._u(query_features), self._u(cands))
        return (1.0 - score).astype(np.float32)

    def rerank_distances_views(
        self, query_features: np.ndarray, candidate_features: Any, views: np.ndarray
    ) -> np.ndarray:
        """[1 + V, K]: `rerank_distances` of the query, then of each of its `views`
        (`query_views`' re-rank images), from one pass over the candidates' spectra.
        `candidate_features` [K, ...], or a list of K rows' features (read in place)."""
        if len(candidate_features) == 0:
            return np.zeros((1 + len(views), 0), np.float32)
        if isinstance(candidate_features, (list, tuple)):
            images: Any = [self._u(f) for f in candidate_features]
        else:
            images = self._u(np.asarray(candidate_features))
        q = self._u(query_features)[None]
        score = aligned_correlations(np.concatenate([q, views]), images)
        return (1.0 - score).astype(np.float32)

    def query_views(
        self, query_features: np.ndarray, offsets: tuple[float, ...]
    ) -> tuple[np.ndarray, np.ndarray]:
        """One query's views: (signatures [V, D], re-rank images [V, R, S]) of its feature
        images re-centred at +-`offsets` m along its y axis (V = 0 with none)."""
        offsets_a = np.asarray(offsets, np.float32).reshape(-1)
        if len(offsets_a) == 0:
            none = np.zeros((0, *np.shape(self._u(query_features))), np.float32)
            return signatures(none, self.crop), none
        positions = np.stack(
            [np.zeros(2 * len(offsets_a), np.float32), np.concatenate([offsets_a, -offsets_a])], 1
        )
        rng = self.bev_config.max_range
        if self.two_channel:
            both = np.stack([self._g(query_features), self._u(query_features)])
            g, u = recentre_kept(both, positions, rng)
        else:
            g = u = recentre_kept(self._g(query_features), positions, rng)
        return signatures(g, self.crop), u
