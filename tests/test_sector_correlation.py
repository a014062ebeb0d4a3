"""The compiled correlations along sectors (`_core.aligned_correlations`,
`_core.yaw_curves`: src/cpp/disco/sector_correlation.*) against the NumPy references of
verify.aligned_correlations and yaw.correlation_curves, at every SIMD level."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import kernel_level

from disco_cli.model import verify, yaw

core = pytest.importorskip("disco_cli._core")
if not hasattr(core, "aligned_correlations"):
    pytest.skip("the compiled core has no aligned_correlations", allow_module_level=True)


def numpy_scores(monkeypatch, q: np.ndarray, c: np.ndarray) -> np.ndarray:
    with monkeypatch.context() as m:
        m.setattr(verify, "BACKEND", "numpy")
        return verify.aligned_correlations(q, c)


def numpy_curves(monkeypatch, q: np.ndarray, m: np.ndarray) -> np.ndarray:
    with monkeypatch.context() as p:
        p.setattr(yaw, "BACKEND", "numpy")
        return yaw.correlation_curves(q, m)


def scenes(views: int, count: int, rings: int, sectors: int, seed: int):
    """Sparse non-negative query images and candidates; candidate 2 is view 0 turned by
    7 sectors plus noise, candidate 3 a copy of the last view (with two or more)."""
    rng = np.random.default_rng(seed)

    def sparse(*shape):
        return rng.random(shape) * (rng.random(shape) < 0.4) + 0.2

    q = sparse(views, rings, sectors).astype(np.float32)
    c = sparse(count, rings, sectors).astype(np.float32)
    if count > 3:
        c[2] = np.roll(q[0], 7, axis=1) + 0.2 * rng.random((rings, sectors))
        c[3] = q[-1] if views > 1 else c[3]
    return q, c


@pytest.mark.parametrize(
    "views, count, rings, sectors",
    [
        (5, 30, 40, 120),
        (5, 10, 40, 120),
        (1, 17, 7, 45),
        (6, 5, 33, 64),
        (2, 40, 16, 121),
        (3, 6, 2, 6),
    ],
)
def test_aligned_correlations_are_the_numpy_reference(
    views, count, rings, sectors, kernel, monkeypatch
):
    q, c = scenes(views, count, rings, sectors, seed=rings + sectors)
    got = core.aligned_correlations(q, c)
    want = numpy_scores(monkeypatch, q, c)
    assert got.shape == (views, count) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=2e-6)
    # The same ranking of the candidates for every view (no ties in these scenes).
    np.testing.assert_array_equal(np.argsort(-got, axis=1), np.argsort(-want, axis=1))
    if count > 3:
        if views > 1:
            assert got[-1, 3] == pytest.approx(1.0, abs=1e-6)  # a copy of the last view
        assert got[0, 2] == got[0].max() and got[0, 2] > 0.9  # view 0 turned


def test_the_levels_agree_to_the_bit(kernel):
    q, c = scenes(5, 30, 40, 120, seed=3)
    got = core.aligned_correlations(q, c)
    curves = core.yaw_curves(q[0], c[:13], yaw.ring_weights(40).astype(np.float32))
    peaks = yaw.estimate_yaw_conf(q[0], c[:13])
    with kernel_level(0):
        np.testing.assert_array_equal(peaks, yaw.estimate_yaw_conf(q[0], c[:13]))
        np.testing.assert_array_equal(got, core.aligned_correlations(q, c))
        np.testing.assert_array_equal(
            curves, core.yaw_curves(q[0], c[:13], yaw.ring_weights(40).astype(np.float32))
        )


def test_empty_images_score_zero_and_nothing_gives_nothing(kernel, monkeypatch):
    q, c = scenes(3, 6, 9, 30, seed=5)
    q[1] = 0.0  # an empty view
    c[4] = 0.0  # an empty candidate
    c[5] = 2.5  # one value everywhere: empty once centred
    got = verify.aligned_correlations(q, c)
    assert (got[1] == 0).all() and (got[:, 4] == 0).all() and (got[:, 5] == 0).all()
    np.testing.assert_allclose(got[:, :5], numpy_scores(monkeypatch, q, c)[:, :5], atol=2e-6)
    assert verify.aligned_correlations(q, c[:0]).shape == (3, 0)
    assert verify.aligned_correlations(q[:0], c).shape == (0, 6)
    assert core.aligned_correlations(q, c[:0]).shape == (3, 0)
    assert core.yaw_curves(q[0], c[:0], yaw.ring_weights(9).astype(np.float32)).shape == (0, 30)


def test_strided_candidates_give_the_contiguous_scores(kernel):
    # The models pass one channel of [K, 2, R, S] features: a view, not a copy.
    q, c = scenes(2, 12, 20, 60, seed=7)
    both = np.stack([c, c[::-1]], axis=1)
    np.testing.assert_array_equal(
        core.aligned_correlations(q, both[:, 0]), core.aligned_correlations(q, c)
    )
    w = yaw.ring_weights(20).astype(np.float32)
    np.testing.assert_array_equal(core.yaw_curves(q[0], both[:, 0], w), core.yaw_curves(q[0], c, w))


@pytest.mark.parametrize("rings, sectors", [(40, 120), (7, 45), (33, 64), (16, 121)])
def test_yaw_curves_are_the_numpy_reference(rings, sectors, kernel, monkeypatch):
    q, c = scenes(1, 21, rings, sectors, seed=sectors)
    got = yaw.correlation_curves(q[0], c)
    want = numpy_curves(monkeypatch, q[0], c)
    assert got.shape == (21, sectors) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=2e-6 * np.abs(want).max())
    np.testing.assert_array_equal(got.argmax(axis=1), want.argmax(axis=1))


@pytest.mark.parametrize("rings, sectors", [(40, 120), (7, 45), (33, 64), (16, 121), (5, 12)])
def test_yaw_conf_is_the_numpy_reference(rings, sectors, kernel, monkeypatch):
    q, c = scenes(1, 21, rings, sectors, seed=sectors + 1)
    c[5:9] = np.roll(q[0], 3 + sectors // 3, axis=1) * np.float32(0.5)  # turned copies
    got_yaw, got_conf = yaw.estimate_yaw_conf(q[0], c)
    with monkeypatch.context() as p:
        p.setattr(yaw, "BACKEND", "numpy")
        want_yaw, want_conf = yaw.estimate_yaw_conf(q[0], c)
    assert got_yaw.dtype == got_conf.dtype == np.float32 and got_yaw.shape == (21,)
    assert ((got_yaw > -180) & (got_yaw <= 180)).all()
    np.testing.assert_allclose(yaw.wrap_deg(got_yaw - want_yaw), 0.0, atol=1e-3)
    np.testing.assert_allclose(got_conf, want_conf, atol=1e-4)
    empty = yaw.estimate_yaw_conf(q[0], c[:0])
    assert empty[0].shape == empty[1].shape == (0,)


def test_a_turned_image_gives_its_yaw_and_a_clear_margin(kernel, monkeypatch):
    # The query is the match rolled by +10 sectors of 3 degrees: yaw -30 (yaw.py's sign).
    rng = np.random.default_rng(11)
    match = (rng.random((40, 120)) * (rng.random((40, 120)) < 0.3)).astype(np.float32)
    others = rng.random((3, 40, 120)).astype(np.float32)
    matches = np.concatenate([match[None], others])
    query = np.roll(match, 10, axis=1)
    got_yaw, got_conf = yaw.estimate_yaw_conf(query, matches)
    with monkeypatch.context() as p:
        p.setattr(yaw, "BACKEND", "numpy")
        want_yaw, want_conf = yaw.estimate_yaw_conf(query, matches)
    assert got_yaw[0] == pytest.approx(-30.0, abs=1e-3)
    assert got_conf[0] > 0.5
    np.testing.assert_allclose(got_yaw, want_yaw, atol=1e-3)
    np.testing.assert_allclose(got_conf, want_conf, atol=1e-4)


def test_the_backend_is_selectable_and_a_core_without_the_kernels_falls_back(monkeypatch):
    q, c = scenes(2, 6, 10, 36, seed=13)
    want = numpy_scores(monkeypatch, q, c)
    want_curves = numpy_curves(monkeypatch, q[0], c)
    monkeypatch.delattr(core, "aligned_correlations")
    monkeypatch.delattr(core, "yaw_conf")
    np.testing.assert_array_equal(verify.aligned_correlations(q, c), want)
    np.testing.assert_array_equal(yaw.correlation_curves(q[0], c), want_curves)
    monkeypatch.setattr(verify, "BACKEND", "fast")
    with pytest.raises(ValueError, match="BACKEND"):
        verify.aligned_correlations(q, c)
    monkeypatch.setattr(yaw, "BACKEND", "fast")
    with pytest.raises(ValueError, match="BACKEND"):
        yaw.correlation_curves(q[0], c)


def test_bad_shapes_are_one_clear_error():
    q = np.zeros((2, 4, 8), np.float32)
    with pytest.raises(ValueError, match="must agree"):
        verify.aligned_correlations(q, np.zeros((3, 4, 9), np.float32))
    with pytest.raises(ValueError, match="R, S >= 1"):
        core.aligned_correlations(q, np.zeros((3, 4, 9), np.float32))
    with pytest.raises(ValueError, match="weights"):
        core.yaw_curves(q[0], q, np.zeros(3, np.float32))


def test_candidates_read_one_by_one_score_as_the_stacked_ones(kernel, monkeypatch):
    """Rows held apart (a cache's arrays, one channel of each) score as their stack
    does, whatever their layout; a candidate of another shape is refused in one line."""
    q, c = scenes(3, 19, 40, 120, seed=11)
    want = core.aligned_correlations(q, c)
    rows = np.stack([np.zeros_like(c), c], axis=1)  # [K, 2, R, S]: the second channel
    apart = [r[1] for r in rows]
    np.testing.assert_array_equal(core.aligned_correlations_at(q, apart), want)
    mixed = [x.astype(np.float64) if k % 3 == 0 else np.asfortranarray(x) for k, x in enumerate(c)]
    np.testing.assert_array_equal(core.aligned_correlations_at(q, mixed), want)
    np.testing.assert_array_equal(verify.aligned_correlations(q, apart), want)
    np.testing.assert_allclose(numpy_scores(monkeypatch, q, apart), want, atol=2e-6)
    assert core.aligned_correlations_at(q, []).shape == (3, 0)
    with pytest.raises(ValueError, match="every candidate must be"):
        core.aligned_correlations_at(q, [c[0], c[1][:, :60]])
