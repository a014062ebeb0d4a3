"""A stand-in model for tests of the query stage (`search.match_queries`): it has
`model.interface.QueryModel`'s members, re-ranks by a number the test stores in each
row's features, and says what it can do in `abilities` and `query_policy`."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from disco_cli.model.interface import Abilities, Unable
from disco_cli.query.query_policy import NO_RERANKING, QueryPolicy


class StubModel(Unable):
    """Re-ranks by feature column 0 of each candidate; yaw 0 unless a test says more.
    Its policy re-ranks `rerank` candidates and switches every other rule off."""

    name = "stub"
    fingerprint = "stub"
    bev_config: Any = None
    abilities = Abilities(rerank=True)

    def __init__(self, rerank: int = 4, **policy: Any):
        self.query_policy: QueryPolicy = replace(NO_RERANKING, rerank_candidates=rerank, **policy)
        self.reranked = 0  # candidates re-ranked, over all calls

    def config_dict(self) -> dict[str, Any]:
        return {"model": self.name}

    def embed(self, bevs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def rerank_distances(self, query_features: Any, features: np.ndarray) -> np.ndarray:
        self.reranked += len(features)
        return np.asarray(features)[:, 0].astype(np.float64)

    def yaw(self, query_features: Any, features: np.ndarray) -> np.ndarray:
        return np.zeros(len(features))

    def yaw_conf(self, query_features: Any, features: np.ndarray) -> tuple[np.ndarray, Any]:
        yaw = self.yaw(query_features, features)
        return yaw, np.full(len(yaw), np.nan)
