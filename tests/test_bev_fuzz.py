"""Fuzzing the voxelizer's boundary: whatever arrives, no crash, and either a
well-formed BEV equal to the NumPy reference or a clear DiscoError."""

from __future__ import annotations

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402
from test_bev import machine_levels, reference_bev  # noqa: E402

from disco_cli import _core  # noqa: E402
from disco_cli.model.bev import (  # noqa: E402
    MODES,
    BEVConfig,
    BEVInputError,
    BEVInputTypeError,
    polar_bev,
    polar_bev_batch,
)

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Values that stress the float fast path: specials, huge, tiny, and exact edges
# of the default grid (ranges 3 and 80, ring edges every 2 m, z edges every 1 m).
SPECIAL = [np.nan, np.inf, -np.inf, 1e30, -1e30, 3e38, 0.0, -0.0, 1e-30, 5e-324, 3.0, 80.0, 2.0,
           -1.5, 18.5, 17.5, 1e-7, -1e-7, 79.99999, 40.0]  # fmt: skip


def coordinates(dtype):
    width = 32 if dtype == np.float32 else 64
    return st.one_of(
        st.sampled_from(SPECIAL),
        st.floats(-100, 100, width=width),
        st.floats(allow_nan=True, allow_infinity=True, width=width),
    )


@st.composite
def scans(draw):
    dtype = draw(st.sampled_from([np.float32, np.float64]))
    n = draw(st.integers(0, 40))
    cols = draw(st.integers(3, 6))
    points = draw(hnp.arrays(dtype, (n, cols), elements=coordinates(dtype)))
    layout = draw(st.sampled_from(["c", "fortran", "row-step", "reversed", "column-slice"]))
    if layout == "fortran":
        points = np.asfortranarray(points)
    elif layout == "row-step":
        points = np.repeat(points, 2, axis=0)[::2]
    elif layout == "reversed":
        points = points[::-1]
    elif layout == "column-slice":
        points = np.hstack([points, points])[:, :cols]  # a view with a longer row stride
    return points


configs = st.one_of(
    st.just(BEVConfig()),
    st.builds(
        BEVConfig,
        rings=st.integers(1, 50),
        sectors=st.integers(1, 200),
        heights=st.integers(1, 30),
        max_range=st.floats(1.0, 200.0),
        min_range=st.floats(0.0, 0.99),
        z_min=st.floats(-5.0, 0.0),
        z_max=st.floats(0.5, 30.0),
        mode=st.sampled_from(MODES),
    ),
)


def check_well_formed(bev: np.ndarray, config: BEVConfig) -> None:
    assert bev.shape == config.shape
    assert bev.dtype == np.float32 and bev.flags.c_contiguous
    assert np.isfinite(bev).all()
    if config.mode == "occupancy":
        assert np.isin(bev, [0.0, 1.0]).all()
    elif config.mode == "density":
        assert bev.min() >= 0.0 and bev.max() <= 1.0
        assert bev.max() in (0.0, 1.0)
    else:
        assert bev.min() >= 0.0 and bev.max() <= np.float32(config.z_max - config.z_min)


@FUZZ
@given(points=scans(), config=configs, level=st.sampled_from(machine_levels()))
def test_any_float_scan_gives_the_reference_bev(points, config, level):
    """On every kernel level this CPU has, each as often (none is drawn twice as its
    best under another number)."""
    previous = _core._set_bev_kernel_level(level)
    try:
        bev = polar_bev(points, config)
    finally:
        _core._set_bev_kernel_level(previous)
    check_well_formed(bev, config)
    expected = reference_bev(points, config)
    assert np.array_equal(bev, expected), np.argwhere(bev != expected)[:5].tolist()


@FUZZ
@given(batch=st.lists(scans(), max_size=4), config=configs, threads=st.integers(0, 3))
def test_any_batch_equals_single_calls(batch, config, threads):
    out = polar_bev_batch(batch, config, threads=threads)
    assert out.shape == (len(batch), *config.shape) and out.dtype == np.float32
    for i, points in enumerate(batch):
        assert np.array_equal(out[i], polar_bev(points, config))


bad_dtypes = st.sampled_from(
    [np.int8, np.int32, np.int64, np.uint16, bool, np.complex64, object, "U3", "S2"]
)


@FUZZ
@given(
    dtype=bad_dtypes,
    shape=st.lists(st.integers(0, 5), min_size=0, max_size=3).map(tuple),
)
def test_wrong_dtypes_raise_a_type_error(dtype, shape):
    points = np.zeros(shape, dtype=dtype)
    with pytest.raises(BEVInputTypeError, match="points"):
        polar_bev(points)


@FUZZ
@given(
    dtype=st.sampled_from([np.float32, np.float64]),
    shape=st.one_of(
        st.tuples(),
        st.tuples(st.integers(0, 5)),
        st.tuples(st.integers(0, 5), st.integers(0, 2)),
        st.tuples(st.integers(0, 3), st.integers(3, 4), st.integers(1, 3)),
    ),
)
def test_wrong_shapes_raise_a_value_error(dtype, shape):
    with pytest.raises(BEVInputError, match="N x 3"):
        polar_bev(np.zeros(shape, dtype=dtype))
