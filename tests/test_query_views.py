"""Query views (issue 24): revisits 4-8 m to the side of the map's route.

The query's feature images re-centred a few metres to either side (`model.query_views`)
join the signature search and the re-ranking (`search.match_queries`), the views' search
on a large map runs on projected signatures (`signature_index.ProjectedSignatures`), and
the yaw search reaches as far to the side (`yaw_refine.SIDE_REACH`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from query_stubs import StubModel
from test_yaw_flip import _features, pose, street, wrap

from disco_cli.maps.database import MatchRows
from disco_cli.maps.signature_index import ProjectedSignatures, SignatureIndex, brute_force_topk
from disco_cli.model import load_model
from disco_cli.model import yaw_refine as yr
from disco_cli.model.interface import Abilities
from disco_cli.model.signature import signatures
from disco_cli.model.verify import aligned_correlation, aligned_correlations
from disco_cli.query.query_views import candidates_with_views, views_search
from disco_cli.query.search import match_queries


def _plain_corr(a: np.ndarray, b: np.ndarray) -> float:
    """Truth by a plain loop: the best centred, normalized correlation over all rolls."""
    a, b = a - a.mean(), b - b.mean()
    norm = np.linalg.norm(a) * np.linalg.norm(b)
    if norm == 0:
        return 0.0
    return max(float((a * np.roll(b, k, axis=1)).sum() / norm) for k in range(b.shape[1]))


def test_aligned_correlations_match_a_plain_loop() -> None:
    rng = np.random.default_rng(0)
    queries = rng.random((3, 6, 16)).astype(np.float32)
    cands = rng.random((5, 6, 16)).astype(np.float32)
    cands[2] = np.roll(queries[1], 5, axis=1)  # a turned copy of view 1: correlation 1
    cands[4] = 0.0  # an empty image correlates with nothing
    got = aligned_correlations(queries, cands)
    want = [[_plain_corr(q, c) for c in cands] for q in queries]
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert got[1, 2] == pytest.approx(1.0, abs=1e-5) and (got[:, 4] == 0).all()
    np.testing.assert_allclose(aligned_correlation(queries[0], cands), got[0], atol=1e-6)
    assert aligned_correlations(queries[:0], cands).shape == (0, 5)
    with pytest.raises(ValueError, match="must agree"):
        aligned_correlations(queries, cands[:, :5])


def test_candidates_keep_the_query_s_own_and_the_views_nearest() -> None:
    # Own candidates 3, 7, 1 (distances 0.5, 0.6, 0.9); the views found 7 nearer (0.2),
    # 4 (0.4), 8 (0.7) and 9 (0.95). With first = 3, the 3 nearest over all are 7, 4 and
    # 3; every own row stays; 8 and 9 are not among the 3 nearest and are left out. The
    # first pass holds those 3 and the query's own 3 (1 too).
    rows, d, first = candidates_with_views(
        np.array([3, 7, 1]),
        np.array([0.5, 0.6, 0.9]),
        np.array([[7, 4], [8, 9], [-1, -1]]),
        np.array([[0.2, 0.4], [0.7, 0.95], [np.inf, np.inf]]),
        first=3,
    )
    assert rows.tolist() == [7, 4, 3, 1] and first == 4
    np.testing.assert_allclose(d, [0.2, 0.4, 0.5, 0.9])


def test_the_first_pass_keeps_the_query_s_own_first_ahead_of_the_rest() -> None:
    # Own 3, 1, 2 (0.5, 0.6, 0.7), first = 1; a view found 4 (0.1) and 2 nearer (0.3).
    # Nearest over all: 4, 2, 3, 1. The first pass is 4 (nearest over all) and 3 (the
    # query's own first), though 2 comes nearer than 3; 2 and 1 follow.
    rows, d, first = candidates_with_views(
        np.array([3, 1, 2]), np.array([0.5, 0.6, 0.7]), np.array([4, 2]), np.array([0.1, 0.3]), 1
    )
    assert rows.tolist() == [4, 3, 2, 1] and first == 2
    np.testing.assert_allclose(d, [0.1, 0.5, 0.3, 0.6])


def _low_rank_signatures(n: int, dim: int, rank: int, seed: int) -> np.ndarray:
    """Unit rows near a `rank`-dimensional subspace, as signatures of one model are
    (their spectra share most of their shape)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, rank)) @ rng.normal(size=(rank, dim)) + 0.01 * rng.normal(size=(n, dim))
    x = x.astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_projected_search_finds_the_exact_neighbours_with_exact_distances() -> None:
    both = _low_rank_signatures(3020, 256, 24, seed=1)
    sigs, queries = both[:3000], both[3000:]
    proj = ProjectedSignatures(sigs, dims=48)
    rows, dists = proj.search(queries, 10)
    hits = 0
    for q, r, d in zip(queries, rows, dists):
        want_r, want_d = brute_force_topk(sigs, q, 10)
        hits += len(set(r.tolist()) & set(want_r.tolist()))
        # Whatever it returns, the distance is the exact one of that row.
        exact = np.linalg.norm(sigs[r].astype(np.float64) - q.astype(np.float64), axis=1)
        np.testing.assert_allclose(d, exact, rtol=1e-5)
        assert (np.diff(d) >= 0).all()
    assert hits >= 0.98 * 20 * 10
    # A row limit and an exclusion mask hold.
    mask = np.zeros(3000, bool)
    mask[::2] = True
    rows, _ = proj.search(queries[:3], 5, limit=[1000, 2000, 3000], exclude=mask)
    assert (rows[0] < 1000).all() and (rows[1] < 2000).all() and (rows[:, :] % 2 == 1).all()


def test_the_views_search_is_exact_unless_asked_to_approximate() -> None:
    both = _low_rank_signatures(1220, 256, 24, seed=3)
    sigs, q = both[:1200], both[1200:]
    index = SignatureIndex(sigs)
    exact_rows, exact_d = views_search(index, q, 5, approximate=False)
    approx_rows, approx_d = views_search(index, q, 5, approximate=True)
    hits = 0
    for qi, er, ed, ar, ad in zip(q, exact_rows, exact_d, approx_rows, approx_d):
        want_r, want_d = brute_force_topk(sigs, qi, 5)
        assert er.tolist() == want_r.tolist()  # exact: the brute force's rows
        np.testing.assert_allclose(ed, want_d, rtol=1e-5)
        # Approximate: the exact distances of the rows it returns, most of them the same.
        true_d = np.linalg.norm(sigs[ar].astype(np.float64) - qi.astype(np.float64), axis=1)
        np.testing.assert_allclose(ad, true_d, rtol=1e-5)
        hits += len(set(ar.tolist()) & set(want_r.tolist()))
    assert hits >= 0.9 * len(q) * 5
    # An index grown row by row (loop detection) would re-project on every row: it
    # answers exactly.
    grown = SignatureIndex(sigs[:0])
    grown.append(sigs)
    rows, _ = views_search(grown, q, 5, approximate=True)
    np.testing.assert_array_equal(rows, exact_rows)


@pytest.fixture(scope="module")
def model():
    return load_model("default")


def test_query_views_are_the_query_re_centred_to_its_sides(model) -> None:
    rng = np.random.default_rng(4)
    f = rng.random((2, 40, 120)).astype(np.float32)
    offsets = model.query_policy.view_offsets
    sigs, images = model.query_views(f, offsets)
    assert sigs.shape[0] == images.shape[0] == 2 * len(offsets)
    positions = np.array([(0.0, s * o) for s in (1, -1) for o in offsets], np.float32)
    positions = positions[
        np.argsort([*range(0, 2 * len(offsets), 2), *range(1, 2 * len(offsets), 2)])
    ]
    # The views, each compared with the plain `recentre` of its position.
    for sig, img in zip(sigs, images):
        found = False
        for p in positions:
            if np.allclose(img, yr.recentre(model._u(f), p[None], 80.0)[0], atol=1e-6):
                g = yr.recentre(model._g(f), p[None], 80.0)
                found = np.allclose(sig, signatures(g, model.crop)[0], atol=1e-6)
                break
        assert found
    with pytest.raises(ValueError, match="lattice"):
        yr.recentre_kept(f[0], np.array([[0.0, 0.3]]), 80.0)


def _revisits(model, s: int, alike: bool, policy=None):
    """A map along a street (every 4 m at y = 0, headed 0) and eight queries 5.5-7.5 m
    to either side, headed along the street either way: their matches and true poses."""
    w = street(s, alike)
    xs = np.arange(-32, 33, 4.0)
    msig, mf = _features(model, w, [pose(x, 0, 0) for x in xs], 100)
    rng = np.random.default_rng(s)
    qp = [
        (
            rng.uniform(-20, 20),
            rng.choice([-1, 1]) * rng.uniform(5.5, 7.5),
            rng.choice([0.0, 180.0]) + rng.uniform(-3, 3),
        )
        for _ in range(8)
    ]
    qsig, qf = _features(model, w, [pose(*q) for q in qp], 500)
    poses = np.c_[xs, np.zeros((len(xs), 3))]

    class Rows:
        def rows(self, ids):
            ids = np.asarray(ids)
            return MatchRows(ids, [f"m{i}" for i in ids], poses[ids], mf[ids])

    index = SignatureIndex(msig)
    found = [
        match_queries(
            index, np.arange(len(xs)), Rows(), model, qsig[i : i + 1], qf[i : i + 1], 1, policy
        )[0][0]
        for i in range(len(qp))
    ]
    # A hit: the match lies within 2 m of the nearest map scan's distance (4 m apart).
    hits = [
        np.hypot(xs[m.row] - q[0], q[1]) <= np.hypot(xs - q[0], q[1]).min() + 2.1
        for m, q in zip(found, qp)
    ]
    errors = [abs(wrap(m.yaw_deg - q[2])) for m, q in zip(found, qp)]
    return np.array(hits), np.array(errors)


def test_revisits_beside_the_route_are_found_with_their_yaw(model, monkeypatch) -> None:
    hits, errors = _revisits(model, 1, alike=False)
    assert hits.all() and errors.max() <= 2.0, (hits, errors.round(1))
    # Without the views, half of them are missed...
    hits_plain, _ = _revisits(model, 1, False, replace(model.query_policy, view_offsets=()))
    assert hits_plain.sum() <= 5
    # ...and with the views but the yaw search reaching 5 m as before, the yaw of some
    # is off by over 2 degrees (the parallax of a sensor 6-8 m away left in it).
    monkeypatch.setattr(yr._coarse_cells.__wrapped__, "__defaults__", (yr.COARSE_REACH, 0.0))
    yr._coarse_cells.cache_clear()
    try:
        _, errors_short = _revisits(model, 1, alike=False)
    finally:
        monkeypatch.undo()
        yr._coarse_cells.cache_clear()
    assert errors_short.max() > 2.0


def test_the_approximate_index_proposes_the_views_candidates_cheaply() -> None:
    pytest.importorskip("faiss")
    from disco_cli.maps.index.ann import AnnIndex, AnnParams

    both = _low_rank_signatures(4010, 1024, 24, seed=5)
    sigs, queries = both[:4000], both[4000:]
    index = AnnIndex.build(sigs, AnnParams(nlist=64, nprobe=16, pca=0, k_factor=10))
    rows, dists = index.approximate_search(queries, 10)
    full, _ = index.search(queries, 10)
    want = [brute_force_topk(sigs, q, 1)[0][0] for q in queries]
    # The nearest scan is among the candidates as often as with the full search (8 of
    # 10 on these signatures); the distances are the index's (8-bit codes: within a few
    # 1e-3 of the exact ones).
    found = sum(w in r for w, r in zip(want, rows))
    assert found >= 7 and found >= sum(w in r for w, r in zip(want, full)) - 1
    exact = np.linalg.norm(sigs[rows[:, 0]] - queries, axis=1)
    np.testing.assert_allclose(dists[:, 0], exact, atol=5e-3)


class _ViewsStub(StubModel):
    """Re-ranks by each row's stored score (feature column 0, the views' images
    ignored); its one side view's signatures are given."""

    abilities = Abilities(rerank=True, query_views=True)

    def __init__(self, view_signatures: np.ndarray):
        super().__init__(rerank=3, view_offsets=(5.0,), view_penalty=0.0)
        self.view_signatures = view_signatures
        self.calls: list[tuple[int, bool]] = []  # (candidates, with the views' images)

    def query_views(self, query_features, offsets):
        return self.view_signatures, np.zeros((len(self.view_signatures), 1))

    def rerank_distances(self, query_features, candidate_features):
        self.calls.append((len(candidate_features), False))
        return candidate_features[:, 0].copy()

    def rerank_distances_views(self, query_features, candidate_features, views):
        # The query's own distance is 0.05 worse than the view's.
        self.calls.append((len(candidate_features), True))
        best = candidate_features[:, 0].astype(np.float64)
        return np.stack([best + 0.05, best])


def test_the_views_add_candidates_and_never_push_out_the_query_s_own() -> None:
    # Rows 0-2 are the query's own 3 nearest signatures; its view's signatures sit on
    # rows 10-12, nearer than any. Row 0 re-ranks best (0.1), the views' rows 0.5-0.7:
    # all six are re-ranked in the first pass of 3 (taking the 3 nearest over the query
    # and its view alone would re-rank rows 10-12 only), and rows 0-2 come first.
    rng = np.random.default_rng(6)
    sigs = rng.random((30, 16)).astype(np.float32)
    query = sigs[0] + 0.01
    sigs[1], sigs[2] = query + 0.02, query - 0.02
    scores = np.full(30, 0.9)
    scores[[0, 1, 2, 10, 11, 12]] = [0.1, 0.3, 0.4, 0.5, 0.6, 0.7]
    feats = np.c_[scores, np.zeros(30)].astype(np.float32)

    class Rows:
        def rows(self, ids):
            ids = np.asarray(ids)
            return MatchRows(
                ids, [f"m{i}" for i in ids], np.full((len(ids), 4), np.nan), feats[ids]
            )

    model = _ViewsStub(sigs[10:13] + 0.001)
    index = SignatureIndex(sigs)
    found = match_queries(index, np.arange(30), Rows(), model, query[None], feats[:1], 3)[0]
    assert [m.row for m in found] == [0, 1, 2]
    # Ranked by, and showing, the best over the query and its views (0.1, 0.3, 0.4):
    # each row's own distance, whatever the others'.
    assert [m.distance for m in found] == pytest.approx([0.1, 0.3, 0.4])
    assert model.calls == [(6, True)]  # one pass of six, with the views' images
