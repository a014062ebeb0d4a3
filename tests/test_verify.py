"""Re-ranking by the aligned correlation of feature images, and the loss that trains it."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.model.verify import aligned_correlation

R, S = 40, 120


def reference_correlation(q: np.ndarray, c: np.ndarray) -> float:
    """Plain loop: the best Pearson-style correlation over every circular roll."""
    q = q - q.mean()
    c = c - c.mean()
    best = -np.inf
    for k in range(q.shape[1]):
        rolled = np.roll(c, k, axis=1)
        best = max(best, float((q * rolled).sum() / (np.linalg.norm(q) * np.linalg.norm(c))))
    return best


def test_aligned_correlation_matches_a_loop_over_rolls():
    rng = np.random.default_rng(0)
    q = rng.random((R, S))
    cands = np.stack([np.roll(q, 17, axis=1), rng.random((R, S)), q + 0.5 * rng.random((R, S))])
    got = aligned_correlation(q, cands)
    want = [reference_correlation(q, c) for c in cands]
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert got[0] == pytest.approx(1.0)  # a rotated copy of itself
    assert got[1] < got[2] < got[0]


def test_aligned_correlation_of_empty_images_is_zero_not_nan():
    z = np.zeros((R, S))
    got = aligned_correlation(z, np.stack([z, np.ones((R, S))]))
    np.testing.assert_array_equal(got, [0.0, 0.0])
    assert aligned_correlation(z, np.zeros((0, R, S))).shape == (0,)
    with pytest.raises(ValueError):
        aligned_correlation(z, np.zeros((2, R, S + 1)))


def test_torch_version_agrees_with_numpy():
    torch = pytest.importorskip("torch")
    from disco_cli.model.verify import aligned_correlation_torch

    rng = np.random.default_rng(1)
    q = rng.random((2, R, S))
    c = rng.random((2, 3, R, S))
    c[0, 1] = np.roll(q[0], -40, axis=1)
    got = aligned_correlation_torch(torch.from_numpy(q).float(), torch.from_numpy(c).float())
    want = np.stack([aligned_correlation(q[b], c[b]) for b in range(2)])
    np.testing.assert_allclose(got.numpy(), want, atol=1e-5)


def test_verify_loss_prefers_the_nearest_candidate():
    torch = pytest.importorskip("torch")
    from disco_cli.training.losses import verify_loss

    dists = torch.tensor([[1.0, 4.0, 7.0]])
    right = verify_loss(torch.tensor([[0.9, 0.5, 0.4]]), dists)
    wrong = verify_loss(torch.tensor([[0.5, 0.9, 0.4]]), dists)
    assert float(right) < 0.05 < float(wrong)
    # By hand: target softmax(-(d - 1) / 0.5), scores / 0.05, cross-entropy.
    t = np.exp(-(np.array([1.0, 4.0, 7.0]) - 1.0) / 0.5)
    t /= t.sum()
    z = np.array([0.5, 0.9, 0.4]) / 0.05
    logp = z - np.log(np.exp(z - z.max()).sum()) - z.max()
    assert float(wrong) == pytest.approx(-(t * logp).sum(), rel=1e-5)


def test_model_reranks_by_its_learned_image_and_keeps_the_yaw():
    pytest.importorskip("torch")
    from test_model import random_bevs, tiny_model

    model = tiny_model()
    assert model.abilities.rerank and model.query_policy.rerank_candidates > 0
    bevs = random_bevs(4, seed=11)
    _, feats = model.embed(bevs)
    # Channel 0 is F_cnn's output, channel 1 its learned part: G - (BEV summed over heights).
    np.testing.assert_allclose(feats[:, 0] - feats[:, 1], bevs.sum(axis=1), atol=1e-4)
    query = feats[2]
    # Candidates: the query's own scan rotated by 24 sectors (+72 degrees) and two others.
    _, rotated = model.embed(np.roll(bevs[2:3], 24, axis=-1))
    cands = np.stack([feats[0], rotated[0], feats[3]])
    dist, yaw = model.rerank(query, cands)
    assert int(np.argmin(dist)) == 1 and dist[1] == pytest.approx(0.0, abs=1e-5)
    assert np.all((dist >= 0) & (dist <= 2))
    # The query BEV is that candidate's rolled by -24 sectors: the query scan is the
    # candidate rotated by -72 degrees, so the yaw of T_match<-query is +72 (docs/model.md).
    np.testing.assert_allclose(yaw, model.yaw(query, cands), atol=1e-6)
    assert yaw[1] == pytest.approx(72.0, abs=0.5)
