"""The polar BEV voxelizer against a plain NumPy implementation of its definition.

The C++ core promises the double-precision definition exactly (it redoes in double
any point its fast float path cannot place with certainty), so every comparison
here is for identical arrays, with no tolerance and no excluded points.
"""

from __future__ import annotations

import ast
import math
import platform
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from disco_cli import _core
from disco_cli.errors import DiscoError
from disco_cli.model.bev import (
    BEVConfig,
    BEVConfigError,
    BEVInputError,
    BEVInputTypeError,
    polar_bev,
    polar_bev_batch,
)

MODES = ("occupancy", "density", "max_height")


def reference_bev(points: np.ndarray, config: BEVConfig) -> np.ndarray:
    """The documented binning, written directly in float64 NumPy."""
    p = np.asarray(points)[:, :3].astype(np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    with np.errstate(over="ignore", invalid="ignore"):
        r = np.sqrt(x * x + y * y)
    keep = (
        (r >= config.min_range) & (r < config.max_range) & (z >= config.z_min) & (z < config.z_max)
    )
    x, y, z, r = x[keep], y[keep], z[keep], r[keep]
    # The platform's libm atan2 (what C++ std::atan2 calls), not np.arctan2: NumPy's
    # SIMD arctan2 differs from libm by 1 ulp on ~7% of inputs, which moves a point
    # lying exactly on a sector edge (see the edge test) into the other sector.
    theta = np.array(
        [math.atan2(b, a) for a, b in zip(x.tolist(), y.tolist(), strict=True)], np.float64
    )
    theta = np.where(theta < 0, theta + 2 * np.pi, theta)
    layers = config.layers
    ring = np.floor(r / (config.max_range / config.rings)).astype(np.int64)
    sector = np.floor(theta / (2 * np.pi / config.sectors)).astype(np.int64)
    height = np.floor((z - config.z_min) / ((config.z_max - config.z_min) / layers)).astype(
        np.int64
    )
    # A value that rounds onto the far edge stays in the last cell.
    ring = np.minimum(ring, config.rings - 1)
    sector = np.minimum(sector, config.sectors - 1)
    height = np.minimum(height, layers - 1)
    out = np.zeros(config.shape, np.float32)
    if config.mode == "occupancy":
        out[height, ring, sector] = 1.0
    elif config.mode == "density":
        np.add.at(out, (height, ring, sector), 1.0)
        if out.max() > 0:
            out /= out.max()
    else:
        np.maximum.at(out, (height, ring, sector), (z - config.z_min).astype(np.float32))
    return out


# The `kernel` fixture (tests/conftest.py) forces each kernel level the CPU has in turn.


def test_every_level_below_the_best_can_be_forced_and_says_which_kernel_ran():
    """The names follow the machine (x86-64: plain, sse2, avx2, avx512; aarch64: plain,
    neon), capping gives each lower level in turn, and the name in use follows the cap."""
    machine = platform.machine().lower()
    expected = (
        ["plain", "sse2", "avx2", "avx512"]
        if machine in ("x86_64", "amd64")
        else ["plain", "neon"]
        if machine in ("aarch64", "arm64")
        else ["plain"]
    )
    previous = _core._set_bev_kernel_level(3)
    try:
        best = _core._bev_kernel_level()
        assert 0 <= best < len(expected)
        if machine in ("x86_64", "amd64", "aarch64", "arm64"):
            assert best >= 1  # SSE2 and NEON are part of these architectures
        names = [_core._bev_kernel_name(level) for level in range(4)]
        assert names[: best + 1] == expected[: best + 1]
        assert all(name == "" for name in names[best + 1 :])
        for level in range(best, -1, -1):
            _core._set_bev_kernel_level(level)
            assert _core._bev_kernel_level() == level
            assert _core._bev_kernel_name() == expected[level]
    finally:
        _core._set_bev_kernel_level(previous)


def machine_levels() -> list[int]:
    """The kernel levels this CPU and build have, best first (what `kernel` runs)."""
    previous = _core._set_bev_kernel_level(3)
    try:
        return list(range(_core._bev_kernel_level(), -1, -1))
    finally:
        _core._set_bev_kernel_level(previous)


def test_every_reference_check_runs_on_every_kernel_level():
    """A test that compares the core with the NumPy reference takes the `kernel`
    fixture, so that every level this CPU has is checked, not only its best."""
    tree = ast.parse(Path(__file__).read_text())
    tests = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")]
    uses = {
        t.name
        for t in tests
        if any(isinstance(n, ast.Name) and n.id == "reference_bev" for n in ast.walk(t))
    }
    assert len(uses) >= 8  # the file was read
    missing = [t.name for t in tests if t.name in uses and "kernel" not in ast.unparse(t.args)]
    assert not missing, missing


def random_scan(rng: np.random.Generator, n: int, dtype=np.float32, cols: int = 4) -> np.ndarray:
    """Points around and beyond the default grid, plus intensity-like extra columns."""
    p = np.empty((n, cols))
    p[:, 0] = rng.uniform(-90, 90, n)
    p[:, 1] = rng.uniform(-90, 90, n)
    p[:, 2] = rng.uniform(-3, 21, n)
    p[:, 3:] = rng.uniform(0, 1, (n, cols - 3))
    return p.astype(dtype)


def assert_same(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.dtype == np.float32 and actual.flags.c_contiguous
    assert actual.shape == expected.shape
    diff = np.argwhere(actual != expected)
    assert diff.size == 0, f"{len(diff)} cells differ, first at {diff[:3].tolist()}"


# -- against the reference ---------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("cols", [3, 4, 6])
def test_random_scans_equal_reference(mode, dtype, cols, kernel):
    rng = np.random.default_rng(hash((mode, cols)) % 2**32)
    config = BEVConfig(mode=mode)
    for _ in range(3):
        points = random_scan(rng, 20_003, dtype, cols)  # not a multiple of 8: tails too
        assert_same(polar_bev(points, config), reference_bev(points, config))


@pytest.mark.parametrize("mode", MODES)
def test_other_grids_equal_reference(mode, kernel):
    rng = np.random.default_rng(7)
    points = random_scan(rng, 20_000)
    for config in (
        BEVConfig(rings=7, sectors=360, heights=3, max_range=50.0, min_range=0.0, mode=mode),
        BEVConfig(
            rings=100, sectors=60, heights=40, z_min=-0.3, z_max=9.7, max_range=33.3, mode=mode
        ),
        BEVConfig(rings=1, sectors=1, heights=1, mode=mode),
    ):
        assert_same(polar_bev(points, config), reference_bev(points, config))


def test_grid_too_big_for_the_simd_kernels_equals_reference(kernel):
    """Above 2^24 cells the SIMD kernels' float cell index is not exact, so the plain
    path takes over (whichever kernel would have run)."""
    config = BEVConfig(rings=4096, sectors=4097, heights=1, mode="density")
    assert config.rings * config.sectors >= 2**24
    points = random_scan(np.random.default_rng(8), 5000)
    assert_same(polar_bev(points, config), reference_bev(points, config))


def test_points_on_and_near_every_edge_equal_reference(kernel):
    """Points at each cell edge and offset from it by 1e-12 .. 1e-3: the band where a
    float fast path would go wrong, so the exact fallback must take over."""
    config = BEVConfig()
    offsets = np.array([0.0, 1e-12, -1e-12, 1e-9, -1e-9, 1e-7, -1e-7, 1e-5, -1e-5, 1e-3, -1e-3])
    rng = np.random.default_rng(3)
    angle_edges = np.arange(config.sectors + 1) * (2 * np.pi / config.sectors)
    ring_edges = np.arange(config.rings + 1) * (config.max_range / config.rings)
    ring_edges = np.concatenate([ring_edges, [config.min_range]])
    z_edges = (
        config.z_min
        + np.arange(config.heights + 1) * (config.z_max - config.z_min) / config.heights
    )
    parts = []
    for dtype in (np.float64, np.float32):
        theta = (angle_edges[:, None] + offsets).ravel()
        r = rng.uniform(config.min_range, config.max_range, theta.size)
        z = rng.uniform(config.z_min, config.z_max, theta.size)
        parts.append(np.stack([r * np.cos(theta), r * np.sin(theta), z], 1).astype(dtype))
        r = (ring_edges[:, None] * (1 + offsets)).ravel()
        theta = rng.uniform(0, 2 * np.pi, r.size)
        z = rng.uniform(config.z_min, config.z_max, r.size)
        parts.append(np.stack([r * np.cos(theta), r * np.sin(theta), z], 1).astype(dtype))
        z = (z_edges[:, None] + offsets).ravel()
        r = rng.uniform(config.min_range, config.max_range, z.size)
        theta = rng.uniform(0, 2 * np.pi, z.size)
        parts.append(np.stack([r * np.cos(theta), r * np.sin(theta), z], 1).astype(dtype))
    for points in parts:
        for mode in MODES:
            cfg = BEVConfig(mode=mode)
            # One point per call, so a wrong cell cannot hide behind another point.
            for p in points[:: max(1, len(points) // 150)]:
                assert_same(polar_bev(p[None], cfg), reference_bev(p[None], cfg))
            assert_same(polar_bev(points, cfg), reference_bev(points, cfg))


@pytest.mark.parametrize("mode", MODES)
def test_real_scans_equal_reference(realdata, mode, kernel):
    config = BEVConfig(mode=mode)
    files = sorted((realdata / "kitti00" / "velodyne").glob("*.bin"))[:2]
    files += sorted((realdata / "hdl32_pair").glob("*.bin"))
    assert files
    for f in files:
        points = np.fromfile(f, np.float32).reshape(-1, 4)
        expected = reference_bev(points, config)
        assert expected.any()
        assert_same(polar_bev(points, config), expected)
        assert_same(polar_bev(points.astype(np.float64), config), expected)


# -- hand-computed values ------------------------------------------------------


def test_one_point_by_hand():
    # r = 14.14 m -> ring 7 (2 m rings); 45 deg -> sector 15 (3 deg); z 0.5 -> layer 2 (1 m).
    bev = polar_bev(np.array([[10.0, 10.0, 0.5]], np.float32))
    assert bev.shape == (20, 40, 120)
    assert np.argwhere(bev).tolist() == [[2, 7, 15]]
    assert bev[2, 7, 15] == 1.0


def test_sector_zero_starts_at_plus_x_and_grows_toward_plus_y():
    cfg = BEVConfig(heights=1)

    def at(deg: float) -> int:
        a = math.radians(deg)
        return int(
            np.argwhere(polar_bev(np.array([[10 * math.cos(a), 10 * math.sin(a), 0.0]]), cfg))[0, 2]
        )

    assert [at(1.5), at(4.5), at(91.5), at(181.5), at(358.5)] == [0, 1, 30, 60, 119]


def test_edges_stay_in_bounds(kernel):
    cfg = BEVConfig(mode="density")
    points = np.array(
        [
            [10.0, -1e-300, 0.0],  # theta = 2 pi - 1e-301 rounds to 2 pi: last sector
            [10.0, -0.0, 0.0],  # atan2(-0, +x) = -0: sector 0
            [80.0, 0.0, 0.0],  # r == max_range: outside
            [0.0, 79.99999999999999, 0.0],  # just inside max_range: last ring
            [3.0, 0.0, 0.0],  # r == min_range: inside, ring 1
            [0.0, 2.9999999, 0.0],  # r just under min_range: outside
            [-20.0, 0.0, 18.5],  # z == z_max: outside
            [-20.0, 0.0, -1.5],  # z == z_min: inside, layer 0
            [-20.0, 0.0, 18.499999999],  # just under z_max: top layer
        ]
    )
    bev = polar_bev(points, cfg)
    cells = {tuple(c) for c in np.argwhere(bev).tolist()}
    assert cells == {(1, 5, 119), (1, 5, 0), (1, 39, 30), (1, 1, 0), (0, 10, 60), (19, 10, 60)}
    assert_same(bev, reference_bev(points, cfg))
    for c in cells:  # one point each, so density is 1 everywhere
        assert bev[c] == 1.0


def test_density_is_count_over_the_largest_count():
    pts = np.array([[10.0, 10.0, 0.5]] * 4 + [[10.0, 10.1, 0.6]] * 2 + [[-10.0, 10.0, 3.5]])
    bev = polar_bev(pts, BEVConfig(mode="density"))
    # The first two groups share cell (2, 7, 15): 6 points; the last is alone.
    assert bev[2, 7, 15] == 1.0
    assert bev[5, 7, 45] == np.float32(1 / 6)  # z 3.5 -> layer 5
    assert np.count_nonzero(bev) == 2


def test_max_height_is_top_point_above_z_min():
    pts = np.array([[10.0, 10.0, 0.5], [10.0, 10.0, 7.25], [10.0, 10.0, 30.0], [-10.0, 10.0, -1.5]])
    bev = polar_bev(pts, BEVConfig(mode="max_height"))
    assert bev.shape == (1, 40, 120)
    assert bev[0, 7, 15] == 8.75  # 7.25 - (-1.5); the 30 m point is above z_max
    assert bev[0, 7, 45] == 0.0  # a point exactly at z_min reads as empty
    assert np.count_nonzero(bev) == 1


def test_nan_and_inf_are_dropped_and_empty_is_zero(kernel):
    good = np.array([[10.0, 10.0, 0.5]], np.float32)
    bad = np.array([[np.nan, 1, 1], [1, np.inf, 1], [10, 10, -np.inf], [np.inf, -np.inf, np.nan]])
    expected = polar_bev(good)
    for mode in MODES:
        cfg = BEVConfig(mode=mode)
        # Enough rows for the SIMD kernels' full groups, not only their scalar tails.
        mixed = np.vstack([bad, good, bad] * 5)
        for dtype in (np.float32, np.float64):
            assert_same(polar_bev(mixed.astype(dtype), cfg), reference_bev(good, cfg))
        assert not polar_bev(np.vstack([bad] * 5), cfg).any()
        assert not polar_bev(np.zeros((0, 4), np.float32), cfg).any()
    assert expected.sum() == 1


# -- rotation ------------------------------------------------------------------


@pytest.mark.parametrize("k", [1, 5, 40, 119, -7])
def test_rotation_by_k_sectors_rolls_the_bev(k, kernel):
    """Points at sector centres (away from edges), rotated by k * 3 degrees."""
    rng = np.random.default_rng(k % 1000)
    n = 3000
    sector = rng.integers(0, 120, n)
    theta = np.radians(sector * 3.0 + 1.5)
    r = rng.uniform(3.5, 79.0, n)
    z = rng.uniform(-1.4, 18.4, n)
    rotated_theta = theta + np.radians(3.0 * k)
    scan = np.stack([r * np.cos(theta), r * np.sin(theta), z], 1)
    turned = np.stack([r * np.cos(rotated_theta), r * np.sin(rotated_theta), z], 1)
    bev = polar_bev(scan)
    assert bev.sum() > 1000
    assert_same(polar_bev(turned), np.roll(bev, k, axis=-1))


# -- input handling --------------------------------------------------------------


def test_non_contiguous_and_wide_inputs_match_contiguous(kernel):
    rng = np.random.default_rng(11)
    base = random_scan(rng, 5000, np.float64, 8)
    expected = polar_bev(np.ascontiguousarray(base[:, :3], dtype=np.float32))
    expected64 = polar_bev(np.ascontiguousarray(base[:, :3]))
    assert_same(expected, reference_bev(base.astype(np.float32), BEVConfig()))
    assert_same(expected64, reference_bev(base, BEVConfig()))
    assert_same(polar_bev(base), expected64)  # N x 8 float64
    assert_same(polar_bev(base.astype(np.float32)[:, :3]), expected)  # column slice
    assert_same(polar_bev(np.asfortranarray(base)), expected64)  # column-major
    doubled = np.repeat(base, 2, axis=0)
    assert_same(polar_bev(doubled[::2]), expected64)  # row step
    assert_same(polar_bev(base[::-1]), expected64)  # negative stride (converted once)
    assert_same(polar_bev(base.astype(">f8")), expected64)  # big-endian (converted once)
    assert_same(
        polar_bev(base.astype(np.float16)), polar_bev(base.astype(np.float16).astype(np.float32))
    )
    assert_same(polar_bev(base[:, :3].tolist()), expected64)  # a nested list


def test_kitti_layout_is_read_without_a_copy():
    """tracemalloc sees NumPy's data buffers: reading an N x 4 float32 (or float64)
    scan must allocate only the output, while a layout C++ cannot read in place
    (big-endian) shows the one conversion, proving the measurement can see a copy."""
    n = 200_000
    rng = np.random.default_rng(5)
    scans = {
        "f32": random_scan(rng, n, np.float32),
        "f64": random_scan(rng, n, np.float64),
        "big-endian": random_scan(rng, n, np.float32).astype(">f4"),
    }
    output_bytes = 20 * 40 * 120 * 4
    polar_bev(scans["f32"])  # warm up imports and caches outside the measurement
    peaks = {}
    for name, scan in scans.items():
        tracemalloc.start()
        polar_bev(scan)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks["f32"] < output_bytes + 64_000, peaks
    assert peaks["f64"] < output_bytes + 64_000, peaks
    assert peaks["big-endian"] >= n * 3 * 4, peaks


@pytest.mark.parametrize(
    "bad, error",
    [
        (np.zeros(6, np.float32), BEVInputError),
        (np.zeros((4, 2), np.float32), BEVInputError),
        (np.zeros((2, 3, 4), np.float32), BEVInputError),
        (np.zeros((4, 3), np.int32), BEVInputTypeError),
        (np.zeros((4, 3), bool), BEVInputTypeError),
        (np.array([[1, 2, "a"]], object), BEVInputTypeError),
        (np.zeros((4, 3), np.complex64), BEVInputTypeError),
        ("points.bin", BEVInputTypeError),
    ],
)
def test_bad_points_raise_clear_errors(bad, error):
    with pytest.raises(error) as info:
        polar_bev(bad)
    assert isinstance(info.value, DiscoError)
    assert isinstance(info.value, ValueError if error is BEVInputError else TypeError)
    assert "points" in str(info.value)


def test_core_rejects_what_the_wrapper_would_convert():
    """The private binding itself never reads memory it does not understand."""
    cfg = _core.BEVConfig()
    with pytest.raises(ValueError):
        _core.polar_bev(np.zeros((5, 4))[::-1], cfg)
    with pytest.raises(TypeError):
        _core.polar_bev(np.zeros((5, 4), np.int64), cfg)
    with pytest.raises(ValueError):
        _core.polar_bev(np.zeros((5, 2)), cfg)
    with pytest.raises(TypeError):
        _core.polar_bev([[1.0, 2.0, 3.0]], cfg)


# -- batch ---------------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_batch_equals_single_calls(mode, kernel):
    rng = np.random.default_rng(21)
    cfg = BEVConfig(mode=mode)
    scans = [
        random_scan(rng, n, dt)
        for n, dt in [(5000, np.float32), (0, np.float32), (300, np.float64)]
    ]
    scans += [random_scan(rng, 4000, np.float64, 6)[::2], random_scan(rng, 2000)[:, :3]]
    expected = np.stack([polar_bev(s, cfg) for s in scans])
    assert_same(expected, np.stack([reference_bev(s, cfg) for s in scans]))
    for threads in (0, 1, 2, 5):
        out = polar_bev_batch(scans, cfg, threads=threads)
        assert out.shape == (len(scans), *cfg.shape)
        assert_same(out, expected)
    assert polar_bev_batch([], cfg).shape == (0, *cfg.shape)


def test_batch_checks_its_arguments():
    with pytest.raises(BEVInputError, match=r"scans\[1\]"):
        polar_bev_batch([np.zeros((3, 3)), np.zeros((3, 2))])
    with pytest.raises(BEVConfigError, match="threads"):
        polar_bev_batch([np.zeros((3, 3))], threads=-1)
    with pytest.raises(BEVInputError, match="list of scans"):
        polar_bev_batch(np.zeros((10, 4)))


# -- configuration -----------------------------------------------------------------------


def test_config_defaults_and_dict_round_trip():
    cfg = BEVConfig()
    assert cfg.to_dict() == {
        "rings": 40, "sectors": 120, "heights": 20, "max_range": 80.0, "min_range": 3.0,
        "z_min": -1.5, "z_max": 18.5, "mode": "occupancy",
    }  # fmt: skip
    other = BEVConfig(rings=10, sectors=36, heights=4, z_max=5.0, mode="max_height")
    assert BEVConfig.from_dict(other.to_dict()) == other
    assert BEVConfig.from_dict({"rings": 10}) == BEVConfig(rings=10)
    assert other.shape == (1, 10, 36)


def test_config_rejects_unknown_keys_and_bad_values():
    with pytest.raises(BEVConfigError, match="unknown BEVConfig key.*ring\\b"):
        BEVConfig.from_dict({"ring": 40})
    bad = [
        ({"rings": 0}, "rings"),
        ({"sectors": -3}, "sectors"),
        ({"heights": 2.5}, "heights"),
        ({"rings": True}, "rings"),
        ({"min_range": 90.0}, "min_range < max_range"),
        ({"min_range": -1.0}, "min_range"),
        ({"z_min": 5.0, "z_max": 5.0}, "z_min < z_max"),
        ({"max_range": float("nan")}, "max_range"),
        ({"mode": "height"}, "mode"),
    ]
    for values, message in bad:
        with pytest.raises(BEVConfigError, match=message):
            BEVConfig(**values)
        with pytest.raises(ValueError):
            BEVConfig.from_dict(values)


def test_core_config_struct_is_bound_field_by_field():
    core = _core.BEVConfig()
    assert (core.rings, core.sectors, core.heights) == (40, 120, 20)
    assert (core.max_range, core.min_range, core.z_min, core.z_max) == (80.0, 3.0, -1.5, 18.5)
    core.rings, core.mode = 5, _core.BEVMode.max_height
    assert core.rings == 5 and core.layers == 1
    core.min_range = 100.0
    with pytest.raises(ValueError, match="min_range"):
        core.validate()
