"""`spectral`: the training-free floor. F_cnn is the identity on the BEV summed over heights.

Its signature is |FFT2| of the per-cell point-layer count and its yaw is plain phase
correlation of those images. It needs no weights and no torch; every learned model has to
beat it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from typing import Any

import numpy as np

from disco_cli.model.bev import BEVConfig
from disco_cli.model.interface import Abilities, Unable
from disco_cli.model.signature import DEFAULT_CROP, signatures
from disco_cli.model.yaw import estimate_yaw, estimate_yaw_conf
from disco_cli.model.yaw_refine import CHECK_BELOW, refine_yaw_conf
from disco_cli.query.query_policy import NO_RERANKING, QueryPolicy


class SpectralModel(Unable):
    """The identity-CNN DiSCO model (see the module docstring): signatures and the yaw,
    plain or parallax-free; no re-ranking."""

    abilities = Abilities(refine_yaw=True)
    query_policy: QueryPolicy = replace(NO_RERANKING, refine_yaw=1)

    def __init__(self, bev_config: Any = None, crop: tuple[int, int] = DEFAULT_CROP):
        if bev_config is None:
            bev_config = BEVConfig()
        self.name = "spectral"
        self.bev_config = bev_config
        self.crop = (int(crop[0]), int(crop[1]))
        blob = json.dumps(self.config_dict(), sort_keys=True).encode()
        self.fingerprint = hashlib.sha256(blob).hexdigest()[:16]

    def config_dict(self) -> dict[str, Any]:
        return {
            "model": self.name,
            "kind": "spectral",
            "crop": list(self.crop),
            "bev_config": self.bev_config.to_dict(),
        }

    def features(self, bevs: np.ndarray) -> np.ndarray:
        b = np.asarray(bevs, dtype=np.float32)
        if b.ndim != 4:
            raise ValueError(f"bevs must be [B, H, R, S], got shape {b.shape}")
        return b.sum(axis=1)

    def embed(self, bevs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        feats = self.features(bevs)
        return signatures(feats, self.crop), feats

    def yaw(self, query_features: np.ndarray, match_features: np.ndarray) -> np.ndarray:
        return estimate_yaw(query_features, match_features)

    def refine_yaw(self, query_features: np.ndarray, match_features: np.ndarray) -> np.ndarray:
        """`yaw` with the parallax of the two sensors' offset removed (yaw_refine.py)."""
        return self.refine_yaw_conf(query_features, match_features)[0]

    def yaw_conf(
        self, query_features: np.ndarray, match_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(`yaw`, its confidence [K] in [0, 1]: yaw.estimate_yaw_conf)."""
        return estimate_yaw_conf(query_features, match_features)

    def refine_yaw_conf(
        self,
        query_features: np.ndarray,
        match_features: np.ndarray,
        check_below: float = CHECK_BELOW,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(`refine_yaw`, its confidence [K] in [0, 1]; the second heading checked below
        `check_below`)."""
        rng = self.bev_config.max_range
        return refine_yaw_conf(query_features, match_features, rng, check_below)
