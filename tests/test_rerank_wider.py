"""The second re-ranking pass: when none of the first candidates matches well, the search
re-ranks the next ones down to the policy's `rerank_wider` (search.match_queries)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from query_stubs import StubModel

from disco_cli.maps.database import MatchRows
from disco_cli.query.query_policy import policy_for
from disco_cli.query.search import SignatureIndex, match_queries

N = 12


class _Db:
    """Map row i holds the re-ranking distance `scores[i]` as its only feature."""

    def __init__(self, scores: np.ndarray):
        self.scores = np.asarray(scores, np.float64)
        self.fetched: list[int] = []

    def rows(self, ids: np.ndarray) -> MatchRows:
        ids = np.asarray(ids)
        self.fetched = [int(i) for i in ids]
        feats = self.scores[ids][:, None]
        return MatchRows(ids, [f"scan{i}" for i in ids], np.zeros((len(ids), 4)), feats)


class _Model(StubModel):
    """Re-ranks by the stored score; yaw = 10 x the row's score (to see it follow the row)."""

    def __init__(self, first: int, wider: int, above: float):
        super().__init__(rerank=first, rerank_wider=wider, rerank_wider_above=above)

    def yaw(self, query_features: np.ndarray, features: np.ndarray) -> np.ndarray:
        return 10.0 * np.asarray(features)[:, 0]


def _search(scores, k=1, first=3, wider=6, above=0.5, rerank=None, rerank_wider=None):
    # Signature i sits at distance i from the query: the signature order is 0, 1, 2, ...
    sigs = np.arange(N, dtype=np.float32)[:, None]
    model, db = _Model(first, wider, above), _Db(scores)
    (found,) = match_queries(
        SignatureIndex(sigs),
        np.arange(N),
        db,
        model,
        np.zeros((1, 1), np.float32),
        np.zeros((1, 1)),
        k,
        policy_for(model, rerank=rerank, rerank_wider=rerank_wider),
    )
    return found, model


def _truth(scores, k, n):
    """The best k of the first n rows by score (ties by row)."""
    order = np.lexsort((np.arange(n), np.asarray(scores[:n])))[:k]
    return [int(i) for i in order]


def test_rerank_goes_wider_when_no_first_candidate_matches_well() -> None:
    scores = np.array([0.9, 0.8, 0.6, 0.7, 0.1, 0.3, 0.05, 0.9, 0.9, 0.9, 0.9, 0.9])
    found, model = _search(scores, k=2)
    # The first three re-rank at best 0.6 > 0.5: rows 3-5 are re-ranked too, not row 6.
    assert [m.row for m in found] == _truth(scores, 2, 6) == [4, 5]
    assert [m.distance for m in found] == [0.1, 0.3]
    assert [m.yaw_deg for m in found] == pytest.approx([1.0, 3.0])
    assert model.reranked == 6


def test_rerank_stays_narrow_when_a_first_candidate_matches_well() -> None:
    scores = np.array([0.9, 0.45, 0.6, 0.7, 0.1, 0.3, 0.05, 0.9, 0.9, 0.9, 0.9, 0.9])
    found, model = _search(scores, k=1)
    # 0.45 <= 0.5: rows 4 and 6, better but beyond the first three, are never looked at.
    assert [m.row for m in found] == _truth(scores, 1, 3) == [1]
    assert model.reranked == 3


def test_explicit_rerank_sets_the_first_pass_and_zero_turns_both_off() -> None:
    scores = np.array([0.9, 0.8, 0.6, 0.7, 0.1, 0.3, 0.05, 0.9, 0.9, 0.9, 0.9, 0.9])
    # --rerank 8 re-ranks 8 (beyond the wider depth 6): one pass, row 6 is found.
    found, model = _search(scores, rerank=8)
    assert [m.row for m in found] == [6] and model.reranked == 8
    # --rerank 0: the signature order.
    found, model = _search(scores, k=3, rerank=0)
    assert [m.row for m in found] == [0, 1, 2] and model.reranked == 0


def test_the_second_pass_runs_only_deeper_than_the_first() -> None:
    scores = np.array([0.9, 0.8, 0.6, 0.7, 0.1, 0.3, 0.05, 0.9, 0.9, 0.9, 0.9, 0.9])
    # A second pass no deeper than the first (3) adds nothing: rows 0-2 alone.
    found, model = _search(scores, wider=3)
    assert [m.row for m in found] == [2] and model.reranked == 3
    # --rerank-wider 0 switches it off.
    found, model = _search(scores, rerank_wider=0)
    assert [m.row for m in found] == [2] and model.reranked == 3
    # A threshold no distance exceeds never triggers it; one below every distance always.
    found, model = _search(scores, above=1.0)
    assert model.reranked == 3
    found, model = _search(np.full(N, 0.2), above=0.1, wider=N)
    assert model.reranked == N


def test_a_wider_pass_on_a_model_without_one_is_refused() -> None:
    from disco_cli.errors import DiscoError

    model = StubModel(rerank=3)  # re-ranks, but its policy has no second pass
    assert policy_for(model, rerank_wider=0).wider == 0  # asking for none is fine
    with pytest.raises(DiscoError, match="stub has no wider re-ranking pass"):
        policy_for(model, rerank_wider=5)
    assert replace(model.query_policy, rerank_wider=8).wider == 8
