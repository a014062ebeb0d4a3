"""Re-ranking with the signature (search.ranking_score): the candidates are ranked by
their re-rank distance less the policy's `signature_weight` over their signature
distance, so a side view that finds the place is not undone by re-rank distances that
are all alike, while far signatures (heavy change) leave the order to the re-ranking."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from query_stubs import StubModel

from disco_cli.io.readers import list_scans, read_scan
from disco_cli.maps.database import MatchRows
from disco_cli.maps.map_side_views import ViewIndex
from disco_cli.query.search import match_queries, ranking_score


def _order(rows, rerank_d, sig_d, weight, floor=0.05):
    return np.lexsort((rows, ranking_score(rerank_d, sig_d, weight, floor))).tolist()


def test_ranking_score_by_hand() -> None:
    rows = np.array([5, 7, 9, 11])
    rerank_d = np.array([0.70, 0.72, 0.71, 0.70])
    sig_d = np.array([0.50, 0.30, 0.45, 0.50])
    # r + 0.3 (1/0.05 - 1/s): 0.70 + 6 - 0.6 = 6.10, 0.72 + 6 - 1 = 5.72,
    # 0.71 + 6 - 0.667 = 6.043, 6.10 (tie: row 5 first)
    assert ranking_score(rerank_d, sig_d, 0.3, 0.05) == pytest.approx(
        [6.1, 5.72, 0.71 + 6 - 0.3 / 0.45, 6.1]
    )
    assert _order(rows, rerank_d, sig_d, 0.3) == [1, 2, 0, 3]
    # Weight 0: the re-rank distance alone, ties by row.
    assert _order(rows, rerank_d, sig_d, 0.0) == [0, 3, 2, 1]
    # Far signatures, as under heavy change: 0.75 - 0.3 / 0.60 = 0.250 against
    # 0.82 - 0.545 = 0.275, 0.80 - 0.526 = 0.274, 0.85 - 0.536 = 0.314 (plus 6 each):
    # the re-ranking's best stays first although its signature is the farthest.
    far = np.array([0.60, 0.55, 0.57, 0.56])
    assert _order(rows, np.array([0.75, 0.82, 0.80, 0.85]), far, 0.3) == [0, 2, 1, 3]
    # A signature at distance 0 (a copy of the query) comes first, with a bounded
    # distance: its re-rank distance, the bonus whole (no division by 0).
    copy = np.array([0.5, 0.5, 0.0, 0.5])
    assert _order(rows, rerank_d, copy, 0.3)[0] == 2
    assert ranking_score(rerank_d, copy, 0.3, 0.05)[2] == pytest.approx(0.71)
    # At or below the floor the bonus stops growing: 0.01 and 0.04 score alike.
    tiny = ranking_score(np.array([0.2, 0.2]), np.array([0.01, 0.04]), 0.3, 0.05)
    assert tiny[0] == tiny[1] == pytest.approx(0.2)


class _Db:
    """Map row i holds its re-rank distance `scores[i]` as its only feature."""

    def __init__(self, scores: np.ndarray):
        self.scores = np.asarray(scores, np.float64)

    def rows(self, ids: np.ndarray) -> MatchRows:
        ids = np.asarray(ids)
        feats = self.scores[ids][:, None]
        return MatchRows(ids, [f"scan{i}" for i in ids], np.zeros((len(ids), 4)), feats)


@pytest.mark.parametrize("weight", [0.0, 0.3])
def test_a_side_view_match_stays_first_through_re_ranking(weight: float) -> None:
    # Scan i's own signature sits at distance 1 + 0.1 i from the query (a query from far
    # to the side matches no scan's own signature well); scan 2's side view sits at 0.2.
    sigs = (1.0 + 0.1 * np.arange(6, dtype=np.float32))[:, None]
    index = ViewIndex(sigs, np.array([2]), np.array([[0.2]], np.float32))
    # Re-rank distances all alike, scan 2's a hair worse than scan 0's.
    scores = np.array([0.70, 0.73, 0.72, 0.74, 0.75, 0.76])
    model = StubModel(rerank=4, signature_weight=weight)
    (found,) = match_queries(
        index, np.arange(6), _Db(scores), model, np.zeros((1, 1), np.float32),
        np.zeros((1, 1)), 3,
    )  # fmt: skip
    # The truth by hand: the 4 re-ranked are scans 0-3 (scan 2 by its view), ranked by
    # score = scores - weight / (0.2 for scan 2, else 1 + 0.1 i).
    sig_d = np.where(np.arange(6) == 2, 0.2, 1.0 + 0.1 * np.arange(6))[:4]
    score = scores[:4] - weight / sig_d
    want = np.lexsort((np.arange(4), score))[:3].tolist()
    assert [m.row for m in found] == want
    assert want[0] == (2 if weight else 0)
    # Shown: each row's own bounded score, r + weight (1/0.05 - 1/s); sorted by it.
    shown = score[want] + weight / 0.05
    assert [m.distance for m in found] == pytest.approx(shown.tolist())


def test_the_policy_reaches_the_report_run() -> None:
    from disco_cli.evaluation.report import model_run
    from disco_cli.model import load_model
    from disco_cli.query.query_policy import policy_for

    model = load_model("default")
    run = model_run(model)
    assert run["rerank_signature_weight"] == run["policy"]["signature_weight"] > 0
    assert run["policy"] == model.query_policy.report()
    lighter = replace(model.query_policy, signature_weight=0.1, view_offsets=(5.0,))
    run = model_run(model, lighter)
    assert run["policy"]["signature_weight"] == 0.1 and run["policy"]["view_offsets"] == [5.0]
    run = model_run(model, policy_for(model, rerank=0))  # --rerank 0: the signature order
    assert "rerank_signature_weight" not in run and run["policy"]["rerank_candidates"] == 0
    # What a model cannot do is left out of the policy it reports.
    spectral = model_run(load_model("spectral"), model.query_policy)
    assert "rerank_signature_weight" not in spectral
    assert spectral["policy"]["rerank_candidates"] == 0 and spectral["policy"]["view_offsets"] == []


def test_query_from_5_to_6_m_beside_a_map_scan_finds_it_in_a_map_with_side_views(
    samples: Path, tmp_path: Path
) -> None:
    """A query that is a map scan's own points seen from 5-6 m to its side (the truth:
    that scan) comes back first from the shipped model in a map with side views at 5 m.
    Ordered by the re-rank distance alone, two of these 27 queries take another scan."""
    from disco_cli import Map

    paths = list_scans(samples / "00")
    clouds = [read_scan(p) for p in paths]
    with Map.create(tmp_path / "m.db", "default", side_views=5.0) as m:
        m.add_many((c, str(p), None) for c, p in zip(clouds, paths))
        for k in range(0, len(clouds), 3):
            for offset in (5.0, -5.0, 6.0):
                query = clouds[k].copy()
                query[:, 1] -= offset
                assert m.query(query, topk=1)[0].name == str(paths[k]), (k, offset)
