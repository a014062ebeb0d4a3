"""The compiled curves of re-centred views (`_core.recentre_curves`) against the NumPy
reference of yaw_refine (the C++ reads, pocketfft, yaw.curves_of_cross_power), and
`refine_checked` on both backends."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import kernel_level

from disco_cli.model import fft, yaw_refine
from disco_cli.model.yaw import ring_weights, wrap_deg

core = pytest.importorskip("disco_cli._core")
if not hasattr(core, "recentre_curves"):
    pytest.skip("the compiled core has no recentre_curves", allow_module_level=True)

MAX_RANGE = 80.0


def reference(image: np.ndarray, match: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """yaw_refine's NumPy path: views read by `_resample`, pocketfft spectra, `_curves`."""
    rings, sectors = image.shape
    places = yaw_refine._places(rings, sectors, MAX_RANGE, positions)
    views = yaw_refine._resample(yaw_refine._padded(image), places, image.shape)
    spectra = fft.rfft(views, axis=-1)
    return yaw_refine._curves(spectra, fft.rfft(match, axis=-1), sectors)


def compiled(image: np.ndarray, match: np.ndarray, positions: np.ndarray) -> np.ndarray:
    rings, sectors = image.shape
    places = yaw_refine._places(rings, sectors, MAX_RANGE, positions)
    lanes = yaw_refine._lane_places(places, rings, sectors)
    table = core.recentre_table(yaw_refine._padded(image), 2 * sectors + 1)
    weights = ring_weights(rings).astype(np.float32)
    rp = yaw_refine._padded_rings(rings)
    return core.recentre_curves(table, 2 * sectors + 1, lanes, match, weights, rp)


def images(rings: int, sectors: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A sparse query and a match that is it turned by 9 sectors plus noise."""
    rng = np.random.default_rng(seed)
    q = (rng.random((rings, sectors)) * (rng.random((rings, sectors)) < 0.3)).astype(np.float32)
    m = np.roll(q, 9, axis=1) + 0.3 * rng.random((rings, sectors), np.float32)
    return q, m.astype(np.float32)


# 17 positions: whole batches of every level's lanes and a tail, the origin included.
POSITIONS = np.array(
    [(x, y) for x in (-3.0, 0.0, 3.0) for y in (-6.0, -1.5, 0.0, 0.5, 6.0)]
    + [(7.5, -8.0), (0.0, 8.0)],
    np.float32,
)


@pytest.mark.parametrize("shape", [(40, 120), (24, 90), (16, 121), (33, 60)])
def test_curves_are_the_numpy_reference_within_float32_error(shape, kernel):
    q, m = images(*shape, seed=shape[0])
    got = compiled(q, m, POSITIONS)
    want = reference(q, m, POSITIONS)
    assert got.shape == want.shape == (len(POSITIONS), shape[1])
    # The curves sum to at most 1 (whitened, weights summing to 1): float32 error.
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    # Same peaks, so the same search decisions.
    np.testing.assert_array_equal(np.argmax(got, axis=1), np.argmax(want, axis=1))


def test_every_level_gives_the_same_curves():
    q, m = images(40, 120, seed=1)
    results = {}
    for level in (0, 1, 2, 3):
        try:
            with kernel_level(level):
                results[level] = compiled(q, m, POSITIONS)
        except pytest.skip.Exception:
            continue
    assert 0 in results and len(results) >= 2
    for level, curves in results.items():
        np.testing.assert_array_equal(curves, results[0], err_msg=f"level {level}")


def test_empty_views_and_no_views():
    """A view that reads only empty cells gives a zero curve (the floor keeps it finite),
    and no views give no curves."""
    q = np.zeros((40, 120), np.float32)
    _, m = images(40, 120, seed=2)
    got = compiled(q, m, POSITIONS[:3])
    assert np.isfinite(got).all() and (got == 0).all()
    weights = ring_weights(40).astype(np.float32)
    table = core.recentre_table(yaw_refine._padded(q), 241)
    none = core.recentre_curves(table, 241, [], m, weights, 48)
    assert none.shape == (0, 120)


def test_bad_input_is_one_clear_error():
    q, m = images(40, 120, seed=3)
    padded = core.recentre_table(yaw_refine._padded(q), 241)
    weights = ring_weights(40).astype(np.float32)
    places = np.zeros((2, 120 * 40), np.float32)
    with pytest.raises(ValueError, match="multiple of 16"):
        core.recentre_curves(padded, 241, [places], m, weights, 40)
    with pytest.raises(ValueError, match="places"):
        core.recentre_curves(padded, 241, [places[:, 1:]], m, weights, 48)
    with pytest.raises(ValueError, match="weights"):
        core.recentre_curves(padded, 241, [places], m, weights[1:], 48)
    # Places outside the table: in whole vectors of rings and in the last ones.
    for cell, ring, sector in [(5, 44.0, 3.0), (39, 2.0, 250.0), (120 * 40 - 1, np.nan, 1.0)]:
        bad = places.copy()
        bad[:, cell] = ring, sector
        with pytest.raises(IndexError):
            core.recentre_curves(padded, 241, [bad], m, weights, 48)


def moved(points: np.ndarray, xy: tuple[float, float], yaw_deg: float) -> np.ndarray:
    """The scan as a sensor at `xy` (in the scan's frame) headed `yaw_deg` would see it."""
    a = np.radians(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    dx, dy = points[:, 0] - xy[0], points[:, 1] - xy[1]
    out = points.copy()
    out[:, 0], out[:, 1] = c * dx + s * dy, -s * dx + c * dy
    return out


CASES = [((0.0, 3.0), 37.0), ((0.5, -2.5), -120.0), ((-2.0, 2.0), 171.0), ((2.5, 0.0), 5.0),
         ((4.0, -1.0), 90.0), ((-6.5, 0.5), -45.0), ((1.0, 7.0), 178.0)]  # fmt: skip


def test_refine_checked_gives_the_numpy_backends_answers(samples, monkeypatch):
    """Scans of the sample taken metres apart and turned: the compiled backend finds the
    NumPy backend's yaw, position and confidence, and the yaw the scans were made with."""
    from disco_cli.io.readers import read_scan
    from disco_cli.model.bev import BEVConfig, polar_bev

    cfg = BEVConfig()
    for scan in ("000010.bin", "000003.bin"):
        points = read_scan(samples / "00" / "velodyne" / scan)
        match = polar_bev(points, cfg).sum(axis=0)
        for xy, yaw in CASES:
            query = polar_bev(moved(points, xy, yaw), cfg).sum(axis=0)
            got = {}
            for backend in (None, "numpy"):
                monkeypatch.setattr(yaw_refine, "BACKEND", backend)
                yaw_refine.forget_kept_views()
                got[backend] = yaw_refine.refine_checked(query, match, cfg.max_range)
            (y1, p1, c1), (y2, p2, c2) = got[None], got["numpy"]
            assert abs(wrap_deg(y1 - y2)) <= 1e-3, (scan, xy, yaw, y1, y2)
            np.testing.assert_array_equal(p1, p2)
            assert c1 == pytest.approx(c2, abs=1e-4)
            assert abs(wrap_deg(y1 - yaw)) <= 1.5, (scan, xy, yaw, y1)


def test_unknown_backend_is_one_clear_error(monkeypatch):
    monkeypatch.setattr(yaw_refine, "BACKEND", "fortran")
    q, m = images(40, 120, seed=4)
    with pytest.raises(ValueError, match="BACKEND"):
        yaw_refine.refine_checked(q, m, MAX_RANGE)


def test_one_curve_steps_are_yaw_pys():
    """The core path's steps on one curve give yaw.py's values to the bit: the yaw of
    its peak (peak_shift, shift_to_yaw), the second peak and the margin; on curves with
    ties, flat tops, peaks at both ends and on every sector count of the tests."""
    from disco_cli.model.yaw import margin, peak_shift, second_peak, shift_to_yaw

    rng = np.random.default_rng(12)
    for sectors in (120, 90, 121, 60, 8):
        for case in range(60):
            curve = rng.normal(size=sectors).astype(np.float32)
            if case % 4 == 1:
                curve = np.round(curve, 1)  # ties
            elif case % 4 == 2:
                curve[[0, -1]] = curve.max() + 1  # the peak wraps round
            elif case % 4 == 3:
                curve[:] = 0.25  # flat
            want = float(shift_to_yaw(peak_shift(curve[None]), sectors)[0])
            assert yaw_refine._yaw_of(curve) == want
            best = int(np.argmax(curve))
            idx, val = second_peak(curve[None], np.array([best]))
            assert yaw_refine._second_peak_of(curve, best) == (int(idx[0]), float(val[0]))
            a, b = float(curve.max()), float(val[0])
            assert yaw_refine._margin(a, b) == float(margin(a, b))


@pytest.mark.parametrize("shape", [(40, 120), (33, 60)])
def test_plain_correlations_are_the_numpy_references(shape, kernel):
    """`_core.recentre_nccs` (the heading check's evidence) against yaw_refine's NumPy
    `_aligned_ncc`: the view turned by -shift, both images centred."""
    q, m = images(*shape, seed=5)
    rings, sectors = shape
    positions = POSITIONS[:6]
    shifts = [0, 9, sectors - 1, 17, 3, sectors // 2]
    places = yaw_refine._places(rings, sectors, MAX_RANGE, positions)
    views = yaw_refine._resample(yaw_refine._padded(q), places, q.shape)
    want = []
    for view, shift in zip(views, shifts):
        a = np.roll(view, -shift, axis=1).astype(np.float64)
        a -= a.mean()
        b = m.astype(np.float64) - m.mean(dtype=np.float64)
        want.append((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
    table = core.recentre_table(yaw_refine._padded(q), 2 * sectors + 1)
    lanes = yaw_refine._lane_places(places, rings, sectors)
    got = core.recentre_nccs(table, 2 * sectors + 1, lanes, m, shifts)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_searches_finish_with_room_for_few_places(monkeypatch):
    """With room for fewer read places than one round needs, the compiled searches still
    finish (the places a call computes are lent to it beyond the budget) and give what
    they give with room for all."""
    q, m = images(40, 120, seed=6)
    m = np.random.default_rng(6).random((40, 120)).astype(np.float32)  # unrelated: checked
    yaw_refine.forget_kept_views()
    roomy = yaw_refine.refine_checked(q, m, MAX_RANGE)
    monkeypatch.setattr(yaw_refine, "PLACES_KEPT_BYTES", 3 * 2 * 40 * 120 * 4)  # 3 positions
    monkeypatch.setattr(yaw_refine, "_places_kept", {})
    yaw_refine.forget_kept_views()
    tight = yaw_refine.refine_checked(q, m, MAX_RANGE)
    assert (tight[0], tight[2]) == (roomy[0], roomy[2])
    np.testing.assert_array_equal(tight[1], roomy[1])
