"""Parallax-free yaw: the re-centred polar image and the yaw of scans taken metres apart."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from disco_cli.io.readers import read_scan
from disco_cli.model.bev import BEVConfig, polar_bev
from disco_cli.model.yaw import estimate_yaw, wrap_deg
from disco_cli.model.yaw_refine import query_in_match_frame, recentre, refine_one, refine_yaw

R, S, MAX_RANGE = 40, 120, 80.0


def reference_recentre(image: np.ndarray, position: tuple[float, float]) -> np.ndarray:
    """Cell by cell: the point at the cell's centre seen from `position`, sampled with
    scipy's linear interpolation (empty beyond the rings on both sides, sectors wrap)."""
    dr, ds = MAX_RANGE / R, 2 * np.pi / S
    out = np.zeros((R, S))
    wrapped = np.concatenate([image, image[:, :1]], axis=1)
    for i in range(R):
        for j in range(S):
            r, t = (i + 0.5) * dr, (j + 0.5) * ds
            x, y = r * np.cos(t) + position[0], r * np.sin(t) + position[1]
            ri = np.hypot(x, y) / dr - 0.5
            si = (np.arctan2(y, x) % (2 * np.pi)) / ds - 0.5
            if si < 0:
                si += S
            out[i, j] = map_coordinates(wrapped, [[ri], [si]], order=1, mode="grid-constant")[0]
    return out


def test_recentre_at_the_origin_is_the_image(kernel):
    img = np.random.default_rng(0).random((R, S)).astype(np.float32)
    got = recentre(img, np.zeros((1, 2)), MAX_RANGE)[0]
    np.testing.assert_allclose(got, img, atol=1e-4)


@pytest.mark.parametrize("position", [(3.0, 0.0), (-1.3, 2.7), (0.4, -4.1)])
def test_recentre_agrees_with_a_cell_by_cell_reference(position, kernel):
    img = np.random.default_rng(1).random((R, S)).astype(np.float32)
    got = recentre(img, np.array([position]), MAX_RANGE)[0]
    np.testing.assert_allclose(got, reference_recentre(img, position), atol=1e-4)


def moved(points: np.ndarray, xy: tuple[float, float], yaw_deg: float) -> np.ndarray:
    """The scan as a sensor at `xy` (in the scan's frame) headed `yaw_deg` would see it."""
    a = np.radians(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    out = points.copy()
    dx, dy = points[:, 0] - xy[0], points[:, 1] - xy[1]
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    return out


def yaw_errors(points: np.ndarray, cases) -> tuple[np.ndarray, np.ndarray, list]:
    """Plain and refined yaw errors (deg) of the scan seen from each (xy, yaw) in `cases`
    against the scan itself, on the training-free images (BEV summed over heights)."""
    cfg = BEVConfig()
    match = polar_bev(points, cfg).sum(axis=0)
    plain, refined, found = [], [], []
    for xy, yaw in cases:
        query = polar_bev(moved(points, xy, yaw), cfg).sum(axis=0)
        plain.append(abs(wrap_deg(estimate_yaw(query, match[None])[0] - yaw)))
        got, where, _ = refine_one(query, match, cfg.max_range)
        refined.append(abs(wrap_deg(got - yaw)))
        found.append(where)
    return np.array(plain), np.array(refined), found


CASES = [((0.0, 3.0), 37.0), ((0.5, -2.5), -120.0), ((-2.0, 2.0), 171.0), ((2.5, 0.0), 5.0)]


def test_scans_metres_apart_get_their_yaw_without_parallax(samples):
    points = read_scan(samples / "00" / "velodyne" / "000010.bin")
    plain, refined, found = yaw_errors(points, CASES)
    # Within a third of a 3-degree sector, and better than the plain phase correlation.
    assert refined.max() <= 1.0 and refined.mean() <= 0.5, refined
    assert refined.mean() < plain.mean(), (refined, plain)
    # The winning position is the match's sensor seen from the query: -xy turned by -yaw.
    for (xy, yaw), where in zip(CASES, found):
        a = np.radians(yaw)
        truth = -np.array(
            [np.cos(a) * xy[0] + np.sin(a) * xy[1], -np.sin(a) * xy[0] + np.cos(a) * xy[1]]
        )
        assert np.hypot(*(where - truth)) <= 1.0, (xy, yaw, where, truth)


def check_query_positions(points: np.ndarray) -> None:
    """`moved` puts the query sensor at xy in the match's frame, headed yaw: that is what
    query_in_match_frame must find, to the search's 0.5 m step."""
    cfg = BEVConfig()
    match = polar_bev(points, cfg).sum(axis=0)
    for xy, yaw in CASES:
        query = polar_bev(moved(points, xy, yaw), cfg).sum(axis=0)
        got_yaw, position = query_in_match_frame(query, match, cfg.max_range)
        assert abs(wrap_deg(got_yaw - yaw)) <= 1.0, (xy, yaw, got_yaw)
        assert np.hypot(*(position - np.array(xy))) <= 0.5, (xy, yaw, position)


def test_query_position_in_the_match_frame(samples):
    check_query_positions(read_scan(samples / "00" / "velodyne" / "000010.bin"))


def test_query_position_on_a_real_scan(realdata):
    check_query_positions(read_scan(sorted((realdata / "kitti00").rglob("*.bin"))[0]))


def test_real_scan_metres_apart_gets_its_yaw(realdata):
    points = read_scan(sorted((realdata / "kitti00").rglob("*.bin"))[0])
    plain, refined, _ = yaw_errors(points, CASES)
    assert refined.max() <= 1.0 and refined.mean() <= 0.5, refined
    assert refined.mean() < plain.mean(), (refined, plain)


def test_refine_yaw_is_batched_and_in_range():
    rng = np.random.default_rng(4)
    match = rng.random((R, S)).astype(np.float32)
    query = np.roll(match, S // 2, axis=-1)  # half a turn: +180, never -180
    got = refine_yaw(query, np.stack([match, np.roll(match, 10, axis=-1)]), MAX_RANGE)
    assert got.shape == (2,)
    assert got[0] == pytest.approx(180.0, abs=0.2)
    # The query is the second match rolled by a further 50 sectors: -150 degrees.
    assert abs(wrap_deg(got[1] + 150.0)) <= 0.2


def test_refine_yaw_option_chooses_which_matches_are_refined(samples_spectral_db, samples):
    """`--refine-yaw 0` prints the plain phase-correlation yaw; `--refine-yaw 2` changes
    the first two matches' yaw to the re-centred one and leaves the third alone."""
    import json

    from typer.testing import CliRunner

    from disco_cli.cli import app
    from disco_cli.model import load_model

    scan = samples / "01" / "velodyne" / "000005.bin"

    def rows(n: int) -> list[dict]:
        args = ["query", str(scan), "--db", str(samples_spectral_db), "--topk", "3"]
        res = CliRunner().invoke(app, [*args, "--refine-yaw", str(n), "--format", "jsonl"])
        assert res.exit_code == 0, res.output
        return [json.loads(line) for line in res.stdout.splitlines()]

    plain_rows, two_rows = rows(0), rows(2)
    matches = [r["match"] for r in plain_rows]
    assert [r["match"] for r in two_rows] == matches
    plain, two = [r["yaw_deg"] for r in plain_rows], [r["yaw_deg"] for r in two_rows]
    # The truth, computed here: plain and re-centred yaw of the query's own images.
    from disco_cli.model.bev import polar_bev

    model = load_model("spectral")
    query = polar_bev(read_scan(scan), model.bev_config).sum(axis=0)
    images = [polar_bev(read_scan(m), model.bev_config).sum(axis=0) for m in matches]
    want_plain = [estimate_yaw(query, im[None])[0] for im in images]
    want_refined = refine_yaw(query, np.stack(images[:2]), model.bev_config.max_range)
    assert plain == pytest.approx(want_plain, abs=0.01)
    assert two[:2] == pytest.approx(list(want_refined), abs=0.01)
    assert two[2] == pytest.approx(want_plain[2], abs=0.01)


def test_negative_refine_yaw_is_one_clear_error(samples_spectral_db, samples):
    from typer.testing import CliRunner

    from disco_cli.cli import app

    scan = samples / "01" / "velodyne" / "000005.bin"
    res = CliRunner().invoke(
        app, ["query", str(scan), "--db", str(samples_spectral_db), "--refine-yaw", "-1"]
    )
    assert res.exit_code != 0
    assert "--refine-yaw" in res.output and "Traceback" not in res.output


def test_map_query_refines_the_yaw_of_as_many_matches_as_asked(samples, tmp_path):
    """Map.query(refine_yaw=N) changes the yaw of the N best matches only; the default
    is the best one."""
    from disco_cli.maps.facade import Map

    points = read_scan(samples / "01" / "velodyne" / "000005.bin")
    with Map.create(tmp_path / "m.db", model="spectral") as m:
        for p in sorted((samples / "00" / "velodyne").glob("*.bin")):
            m.add(read_scan(p), name=p.name)
        plain = m.query(points, topk=3, refine_yaw=0)
        one = m.query(points, topk=3)
        three = m.query(points, topk=3, refine_yaw=3)
    assert [x.name for x in plain] == [x.name for x in one] == [x.name for x in three]
    assert one[0].yaw_deg == pytest.approx(three[0].yaw_deg, abs=1e-4)
    assert one[1].yaw_deg == pytest.approx(plain[1].yaw_deg, abs=1e-4)
    assert one[0].yaw_deg != pytest.approx(plain[0].yaw_deg, abs=1e-4)
    assert [x.yaw_deg for x in three[1:]] != pytest.approx([x.yaw_deg for x in plain[1:]], abs=1e-4)


def test_shipped_network_re_centres_the_bev_it_was_given(samples):
    """The residual network's `refine_yaw` re-centres G - U, which is the BEV summed over
    heights: the same yaw as re-centring that sum computed here directly."""
    from disco_cli.model import load_model

    model = load_model("default")
    if not getattr(model, "two_channel", False):
        pytest.skip("the default model is not a residual (two-channel) network")
    q = polar_bev(read_scan(samples / "01" / "velodyne" / "000005.bin"), model.bev_config)
    m = polar_bev(read_scan(samples / "00" / "velodyne" / "000004.bin"), model.bev_config)
    fq, fm = model.features(np.stack([q, m]))
    got = model.refine_yaw(fq, fm[None])
    want = refine_yaw(q.sum(axis=0), m.sum(axis=0)[None], model.bev_config.max_range)
    assert got == pytest.approx(want, abs=0.02)


def test_core_resampling_refuses_places_outside_the_image(kernel):
    """The C++ reads check their places: a bad one is an error, not a stray read."""
    from disco_cli import _core

    padded = np.zeros((R + 3) * (2 * S + 1), np.float32)
    for ring, sector in [(R + 2.5, 3.0), (-0.5, 3.0), (2.0, 2 * S + 0.5), (np.nan, 1.0)]:
        places = np.ones((2, R * S), np.float32)
        places[:, 7] = ring, sector
        with pytest.raises(IndexError):
            _core.resample_views(padded, 2 * S + 1, [places], R * S)
    with pytest.raises(ValueError):
        _core.resample_views(padded, 2 * S + 1, [np.ones((3, R * S), np.float32)], R * S)


def reference_resample(padded: np.ndarray, width: int, places: np.ndarray) -> np.ndarray:
    """polar_resample.hpp's bilinear read in float32 NumPy, each operation rounded as
    written there."""
    ring, sector = places
    r0, s0 = ring.astype(np.int64), sector.astype(np.int64)  # truncation, places >= 0
    fr = ring - r0.astype(np.float32)
    fs = sector - s0.astype(np.float32)
    i0 = r0 * width + s0
    a0, a1 = padded[i0], padded[i0 + 1]
    b0, b1 = padded[i0 + width], padded[i0 + width + 1]
    near = a0 + (a1 - a0) * fs
    far = b0 + (b1 - b0) * fs
    return near + (far - near) * fr


@pytest.mark.parametrize("cells", [1, 8, 13, R * S + 5])
def test_core_resampling_equals_the_numpy_definition(cells, kernel):
    """Every SIMD level reads the same float32 values as the definition, to the bit:
    places anywhere in the image up to just below its last ring and sector, and cell
    counts that are not whole vectors."""
    from disco_cli import _core

    rng = np.random.default_rng(cells)
    rows, width = R + 3, 2 * S + 1
    padded = rng.normal(scale=3.0, size=rows * width).astype(np.float32)
    views = []
    for _ in range(3):
        ring = rng.uniform(0.0, rows - 1, cells).astype(np.float32)
        sector = rng.uniform(0.0, width - 1, cells).astype(np.float32)
        ring[::5] = np.floor(ring[::5])  # whole places: fraction 0
        edge = np.nextafter(np.float32(rows - 1), np.float32(0))
        side = np.nextafter(np.float32(width - 1), np.float32(0))
        ring[-1], sector[0] = edge, side
        views.append(np.stack([np.minimum(ring, edge), np.minimum(sector, side)]))
    got = _core.resample_views(padded, width, views, cells)
    want = np.stack([reference_resample(padded, width, v) for v in views])
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


def test_kept_views_give_what_a_fresh_search_gives():
    """The query's views are kept between its matches; the yaw, position and confidence
    against each match are those of a search that starts from nothing."""
    from disco_cli.model.yaw_refine import forget_kept_views, refine_checked

    rng = np.random.default_rng(5)
    query = rng.random((R, S)).astype(np.float32) * (rng.random((R, S)) < 0.3)
    matches = [np.roll(query, k, axis=1) + 0.3 * rng.random((R, S), np.float32) for k in (9, 70)]
    matches.append(rng.random((R, S)).astype(np.float32))  # unrelated: the check runs
    fresh = []
    for m in matches:
        forget_kept_views()
        fresh.append(refine_checked(query, m, MAX_RANGE))
    forget_kept_views()
    for m, (yaw, pos, conf) in zip(matches, fresh):
        got = refine_checked(query, m, MAX_RANGE)
        assert got[0] == yaw and got[2] == conf
        np.testing.assert_array_equal(got[1], pos)


def test_searches_on_several_threads_give_what_one_thread_gives():
    """The kept views are shared by every thread: queries refined side by side (as
    `Map.query` may be called) come back as they do one at a time."""
    from concurrent.futures import ThreadPoolExecutor

    from disco_cli.model.yaw_refine import forget_kept_views, refine_checked

    rng = np.random.default_rng(9)
    queries = [rng.random((R, S)).astype(np.float32) for _ in range(3)]
    pairs = [
        (q, np.roll(q, k, axis=1) + 0.5 * rng.random((R, S), np.float32))
        for q in queries
        for k in (4, 50)
    ]
    pairs += [(q, rng.random((R, S)).astype(np.float32)) for q in queries]
    alone = []
    for q, m in pairs:
        forget_kept_views()
        alone.append(refine_checked(q, m, MAX_RANGE))
    forget_kept_views()
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda p: refine_checked(p[0], p[1], MAX_RANGE), pairs * 3))
    for (yaw, pos, conf), (y2, p2, c2) in zip(alone * 3, together):
        assert (yaw, conf) == (y2, c2)
        np.testing.assert_array_equal(pos, p2)


@pytest.mark.parametrize("sectors", [90, 121])
def test_yaw_of_a_turned_image_on_other_grids(sectors):
    """An image turned by whole sectors comes back with that yaw on grids of other
    sizes, odd sector counts included (the spectra of odd lengths)."""
    from disco_cli.model.yaw_refine import refine_checked

    rng = np.random.default_rng(3)
    img = (rng.random((24, sectors)) < 0.15).astype(np.float32) * rng.random(
        (24, sectors), np.float32
    )
    img[:, : sectors // 3] += 0.5  # one heavy side: a clear heading
    shift = 17
    yaw, _, _ = refine_checked(np.roll(img, shift, axis=1), img, MAX_RANGE)
    assert abs(wrap_deg(yaw + shift * 360.0 / sectors)) < 360.0 / sectors


def test_read_places_kept_within_their_budget(monkeypatch):
    """With room for only a few positions' read places (a large grid), the kept ones are
    dropped and kept afresh, and the searches give what they give with room for all."""
    from disco_cli.model import yaw_refine

    rng = np.random.default_rng(11)
    pairs = [
        (rng.random((R, S)).astype(np.float32), rng.random((R, S)).astype(np.float32))
        for _ in range(3)
    ]
    roomy = []
    for q, m in pairs:
        yaw_refine.forget_kept_views()
        roomy.append(yaw_refine.refine_checked(q, m, MAX_RANGE))
    monkeypatch.setattr(yaw_refine, "PLACES_KEPT_BYTES", 20 * 2 * R * S * 4)  # 20 positions
    monkeypatch.setattr(yaw_refine, "_places_kept", {})
    for (q, m), (yaw, pos, conf) in zip(pairs, roomy):
        yaw_refine.forget_kept_views()
        got = yaw_refine.refine_checked(q, m, MAX_RANGE)
        assert (got[0], got[2]) == (yaw, conf)
        np.testing.assert_array_equal(got[1], pos)
        assert len(yaw_refine._places_kept[(R, S, MAX_RANGE)]) <= 20 + 68
