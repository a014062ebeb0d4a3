"""What the query stage asks of a model: one typed protocol, and what the model can do.

Every model (DiSCO, the spectral floor, Scan Context, a test's stand-in) has all of
`QueryModel`'s members. What it cannot do, `abilities` says, and its `query_policy`
switches that off; the query stage reads both and never asks a model by name what it
has. A model without an ability may take `Unable`'s members, which refuse.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from disco_cli.errors import ModelError
from disco_cli.query.query_policy import QueryPolicy

__all__ = ["Abilities", "QueryModel", "Unable"]


@dataclass(frozen=True)
class Abilities:
    """What a model can do beyond a signature and a yaw."""

    rerank: bool = False  # rerank_distances
    refine_yaw: bool = False  # refine_yaw_conf
    locate: bool = False  # query_position_conf: the snap needs it
    query_views: bool = False  # query_views, rerank_distances_views


class QueryModel(Protocol):
    name: str
    fingerprint: str
    bev_config: Any
    abilities: Abilities
    query_policy: QueryPolicy

    def config_dict(self) -> dict[str, Any]: ...

    def embed(self, bevs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(signatures [B, D], features [B, ...]) of BEVs [B, H, R, S]."""
        ...

    def yaw_conf(
        self, query_features: np.ndarray, match_features: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(yaw [K] in degrees, (-180, 180], of the query in each match's frame; its
        confidence [K] in [0, 1], NaN where the model has none)."""
        ...

    def rerank_distances(
        self, query_features: np.ndarray, candidate_features: np.ndarray
    ) -> np.ndarray:
        """Re-rank distances [K] of the candidates, lower is better."""
        ...

    def rerank_distances_views(
        self, query_features: np.ndarray, candidate_features: np.ndarray, views: np.ndarray
    ) -> np.ndarray:
        """[1 + V, K]: the query's own re-rank distances, then each view's (`views`: the
        re-rank images of `query_views`)."""
        ...

    def query_views(
        self, query_features: np.ndarray, offsets: tuple[float, ...]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(signatures [V, D], re-rank images [V, ...]) of the query re-centred at
        +-each offset (m) along its y axis; V = 2 * len(offsets)."""
        ...

    def refine_yaw_conf(
        self, query_features: np.ndarray, match_features: np.ndarray, check_below: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """`yaw_conf` without the parallax of the two sensors' offset; the best other
        heading is searched too where the confidence is below `check_below`."""
        ...

    def query_position_conf(
        self, query_features: np.ndarray, match_features: np.ndarray, check_below: float
    ) -> tuple[float, np.ndarray, float]:
        """(yaw, position [2] of the query sensor in the match's frame (m), confidence),
        the heading checked as `refine_yaw_conf`'s."""
        ...


class Unable:
    """`QueryModel`'s optional members for a model without them: each refuses (the
    query stage never calls them where `abilities` says no)."""

    name: str

    def _refuse(self, what: str) -> ModelError:
        return ModelError(f"model {self.name} cannot {what}")

    def rerank_distances(self, query_features: Any, candidate_features: Any) -> np.ndarray:
        raise self._refuse("re-rank")

    def rerank_distances_views(self, query_features: Any, candidates: Any, views: Any) -> Any:
        raise self._refuse("re-rank with views of the query")

    def query_views(self, query_features: Any, offsets: Any) -> Any:
        raise self._refuse("make views of the query")

    def refine_yaw_conf(self, query_features: Any, match_features: Any, check_below: Any) -> Any:
        raise self._refuse("refine the yaw")

    def query_position_conf(self, query_features: Any, match_features: Any, check: Any) -> Any:
        raise self._refuse("estimate the query's position")
