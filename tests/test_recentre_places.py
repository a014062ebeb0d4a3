"""Where the compiled searches' re-centred views read (`_core.recentre_places`, through
`recentre_places.compiled`) against NumPy's `yaw_refine._places`: rings to the bit, and
sectors as a correctly rounded float32 arctan2 gives them, at every kernel level."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.model import recentre_places, yaw_refine

core = pytest.importorskip("disco_cli._core")
if not hasattr(core, "recentre_places"):
    pytest.skip("the compiled core has no recentre_places", allow_module_level=True)

RINGS, SECTORS, MAX_RANGE = 40, 120, 80.0  # the default model's bev_config


@pytest.fixture(scope="module")
def lattice():
    """Every lattice position, NumPy's places [M, 2, R * S] of them, and the sectors from
    a float64 arctan2 rounded to float32 (the correctly rounded value but for ties)."""
    side = yaw_refine._LATTICE_SIDE
    index = np.arange(side * side)
    positions = yaw_refine._metres(np.stack([index // side, index % side], axis=1))
    numpy_places = np.stack(yaw_refine._places(RINGS, SECTORS, MAX_RANGE, positions))
    x0, y0 = yaw_refine._grid(RINGS, SECTORS, MAX_RANGE)
    x = (x0[None] + positions[:, 0, None, None]).astype(np.float64)
    y = (y0[None] + positions[:, 1, None, None]).astype(np.float64)
    angle = np.arctan2(y, x).astype(np.float32).reshape(len(positions), -1)
    rounded = angle * np.float32(SECTORS / (2 * np.pi)) + np.float32(SECTORS - 0.5)
    return positions, numpy_places, rounded


def ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many float32 steps apart (positive values of one sign, as the sectors are)."""
    assert (a > 0).all() and (b > 0).all()
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


def test_places_of_every_lattice_position_are_numpys(lattice, kernel):
    positions, numpy_places, rounded = lattice
    got = np.stack(recentre_places.compiled(core, RINGS, SECTORS, MAX_RANGE, positions, False))
    assert got.shape == numpy_places.shape and got.dtype == np.float32
    np.testing.assert_array_equal(got[:, 0].view(np.int32), numpy_places[:, 0].view(np.int32))
    # The arctan2 is correctly rounded but where the true angle lies within its error
    # (1e-12) of a tie: 1 cell in 5 million here, 1 step off.
    off = ulps(got[:, 1], rounded)
    assert off.max() <= 1 and np.count_nonzero(off) <= 5, np.count_nonzero(off)
    # NumPy's float32 arctan2 is not (SVML's on AVX-512: up to 3 steps before scaling,
    # about 1 sector in 11 off): 2 steps at most, and most sectors the same.
    to_numpy = ulps(got[:, 1], numpy_places[:, 1])
    assert to_numpy.max() <= 2 and np.count_nonzero(to_numpy) <= 0.15 * to_numpy.size


def test_the_searches_layout_is_sector_major(kernel):
    positions = np.array([[0.0, 0.0], [-3.5, 7.0], [8.0, -0.5]], np.float32)
    rows = recentre_places.compiled(core, RINGS, SECTORS, MAX_RANGE, positions, False)
    lanes = recentre_places.compiled(core, RINGS, SECTORS, MAX_RANGE, positions, True)
    for row, lane in zip(rows, lanes):
        np.testing.assert_array_equal(lane, yaw_refine._lane_places([row], RINGS, SECTORS)[0])


def test_arctan2_at_the_axes_diagonals_and_octant_borders(kernel):
    """Scale 1 and shift 0: the sectors are the float32 arctan2 itself, against NumPy's
    float64 one rounded (signed zeros and the origin as NumPy takes them)."""
    t = np.float32(np.tan(np.pi / 8))
    pairs = [(0, 0), (0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, 1), (1, -1), (-1, -1),
             (1, t), (t, 1), (-t, 1), (1, -t), (-1, np.nextafter(t, 1)), (3e-7, -5.0),
             (-0.0, -2.0), (0.0, -2.0), (-70.5, 1e-6), (79.9, -79.9)]  # fmt: skip
    y = np.array([p[0] for p in pairs], np.float32)
    x = np.array([p[1] for p in pairs], np.float32)
    here = np.full((1, 2), -0.0, np.float32)  # v + -0 is v, -0 included
    got = core.recentre_places(x, y, here, 1.0, 1e9, 1.0, 0.0)[0]
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64)).astype(np.float32)
    np.testing.assert_array_equal(got[1], want)
    np.testing.assert_array_equal(got[0], np.sqrt(x * x + y * y) + np.float32(0.5))


def test_every_level_gives_the_same_bits():
    from conftest import kernel_level  # deferred: the levels are forced one at a time

    rng = np.random.default_rng(3)
    positions = (rng.integers(-16, 17, (9, 2)) * 0.5).astype(np.float32)
    got = {}
    for level in (0, 1, 2, 3):
        try:
            with kernel_level(level):
                out = recentre_places.compiled(core, RINGS, SECTORS, MAX_RANGE, positions, True)
                got[level] = np.stack(out).view(np.int32)
        except pytest.skip.Exception:
            continue
    assert len(got) >= 2
    for out in got.values():
        np.testing.assert_array_equal(out, got[0])


def test_bad_input_is_one_clear_error():
    x = np.zeros(4, np.float32)
    with pytest.raises(ValueError, match="same length"):
        core.recentre_places(x, x[:3], np.zeros((1, 2), np.float32), 1.0, 2.0, 1.0, 0.0)
    with pytest.raises(ValueError, match=r"\[M, 2\]"):
        core.recentre_places(x, x, np.zeros((1, 3), np.float32), 1.0, 2.0, 1.0, 0.0)


def test_refine_checked_finds_the_same_with_numpys_places(monkeypatch):
    """The compiled searches with the C++ places and with NumPy's: the same position,
    the yaw and the confidence within float32 rounding of the views."""
    rng = np.random.default_rng(5)
    for seed in range(3):
        q = (rng.random((RINGS, SECTORS)) * (rng.random((RINGS, SECTORS)) < 0.3)).astype(np.float32)
        m = np.roll(q, 7 + seed, axis=1) + 0.2 * rng.random((RINGS, SECTORS), np.float32)
        got = []
        for places in (recentre_places.compiled, numpy_compiled):
            monkeypatch.setattr(recentre_places, "compiled", places)
            monkeypatch.setattr(yaw_refine, "_places_kept", {})
            yaw_refine.forget_kept_views()
            got.append(yaw_refine.refine_checked(q, m.astype(np.float32), MAX_RANGE))
        (y1, p1, c1), (y2, p2, c2) = got
        assert abs(y1 - y2) <= 1e-3
        np.testing.assert_array_equal(p1, p2)
        assert c1 == pytest.approx(c2, abs=1e-4)


def numpy_compiled(core, rings, sectors, max_range, positions, lanes):
    places = yaw_refine._places(rings, sectors, max_range, positions)
    return yaw_refine._lane_places(places, rings, sectors) if lanes else places
