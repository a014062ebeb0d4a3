"""Side views (`map_side_views.py`, `build-db --side-views`): a map scan's signatures seen
from beside it take part in the search and answer for the scan itself."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.embedding.load import side_view_bevs
from disco_cli.io.readers import list_scans, read_scan
from disco_cli.maps.map_side_views import ViewIndex, side_offsets
from disco_cli.query.search import brute_force_topk


def run(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, list(args))
    return res.exit_code, res.output


def scan_best_distances(sigs, owner, views, q):
    """Plain reference: each scan's distance is the smallest over its own signature and
    its views'; order by that, ties by row."""
    _, d_own = brute_force_topk(sigs, q, len(sigs))
    best = np.empty(len(sigs))
    best[brute_force_topk(sigs, q, len(sigs))[0]] = d_own
    if len(views):
        order, d_view = brute_force_topk(views, q, len(views))
        for row, d in zip(order, d_view):
            best[owner[row]] = min(best[owner[row]], d)
    return best


@pytest.mark.parametrize("views_per_scan", [0, 1, 2, 4])
def test_view_index_answers_each_scan_once_at_its_closest_signature(views_per_scan):
    rng = np.random.default_rng(views_per_scan)
    n, dim = 60, 16
    sigs = rng.normal(size=(n, dim)).astype(np.float32)
    owner = np.repeat(np.arange(n), views_per_scan)
    views = rng.normal(size=(len(owner), dim)).astype(np.float32)
    index = ViewIndex(sigs, owner, views)
    queries = rng.normal(size=(5, dim)).astype(np.float32)
    rows, dists = index.search(queries, 7)
    for i, q in enumerate(queries):
        best = scan_best_distances(sigs, owner, views, q)
        want = np.argsort(best, kind="stable")[:7]
        assert rows[i].tolist() == want.tolist()
        np.testing.assert_allclose(dists[i], best[want], rtol=1e-5)


def test_view_index_limit_and_exclude_refer_to_scans():
    rng = np.random.default_rng(7)
    n, dim = 30, 8
    sigs = rng.normal(size=(n, dim)).astype(np.float32)
    owner = np.repeat(np.arange(n), 2)
    views = rng.normal(size=(2 * n, dim)).astype(np.float32)
    index = ViewIndex(sigs, owner, views)
    q = rng.normal(size=(2, dim)).astype(np.float32)
    exclude = np.zeros(n, bool)
    exclude[::3] = True
    rows, _ = index.search(q, 5, limit=[20, 10], exclude=exclude)
    for i, lim in enumerate((20, 10)):
        best = scan_best_distances(sigs, owner, views, q[i])
        best[lim:] = np.inf
        best[exclude] = np.inf
        want = np.argsort(best, kind="stable")[:5]
        assert rows[i].tolist() == want.tolist()
        assert not exclude[rows[i]].any() and (rows[i] < lim).all()


def test_side_offsets():
    assert side_offsets(0) == ()
    assert side_offsets(2.5) == (2.5, -2.5)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            side_offsets(bad)


def test_a_view_is_the_scan_seen_from_beside_it(samples):
    """Points seen from a sensor moved `offset` m along y: a point at (x, offset + dy, z)
    lands where (x, dy, z) lands seen from the real sensor."""
    from disco_cli.model.bev import BEVConfig, polar_bev

    cfg = BEVConfig()
    rng = np.random.default_rng(3)
    rel = np.c_[rng.uniform(-60, 60, (500, 2)), rng.uniform(-1.5, 3.0, 500), np.ones(500)]
    rel = rel.astype(np.float32)
    for offset in (2.0, -2.0):
        seen = rel.copy()
        seen[:, 1] += offset
        np.testing.assert_array_equal(side_view_bevs(seen, cfg, (offset,))[0], polar_bev(rel, cfg))
    real = read_scan(list_scans(samples / "00")[3])
    views = side_view_bevs(real, cfg, (2.0, -2.0))
    assert views.shape == (2, *polar_bev(real, cfg).shape)
    assert not np.array_equal(views[0], polar_bev(real, cfg))
    assert not np.array_equal(views[0], views[1])


def test_query_from_beside_a_map_scan_finds_it_at_distance_zero(samples, tmp_path):
    """A query taken exactly where a side view looks from (the map scan's points re-centred
    2.5 m to its left) matches that scan with distance ~0 only in a map with side views."""
    from disco_cli import Map

    paths = list_scans(samples / "00")
    clouds = [read_scan(p) for p in paths]
    query = clouds[10].copy()
    query[:, 1] -= 2.5
    found = {}
    for views in (0.0, 2.5):
        with Map.create(tmp_path / f"m{views}.db", "spectral", side_views=views) as m:
            m.add_many((c, str(p), None) for c, p in zip(clouds, paths))
            assert m.side_views == views and len(m) == len(paths)
            found[views] = m.query(query, topk=3, rerank=0)
    assert found[2.5][0].name == str(paths[10])
    assert found[2.5][0].distance < 1e-3
    assert found[0.0][0].distance > 100 * max(found[2.5][0].distance, 1e-6)
    names = [mt.name for mt in found[2.5]]
    assert len(set(names)) == len(names)  # each scan at most once


def test_build_db_with_side_views_cli(samples, tmp_path):
    db = tmp_path / "map.db"
    scans = list_scans(samples / "00")
    code, out = run("build-db", *map(str, scans[:12]), "-o", str(db), "--side-views", "3")
    assert code == 0, out
    code, out = run("info", str(db), "--format", "jsonl", "--check")
    info = json.loads(out)
    assert code == 0 and info["side_views_m"] == 3.0 and info["check"] == "ok"
    # Adding keeps the map's setting; another setting is refused in one line, untouched.
    code, out = run("build-db", *map(str, scans[12:16]), "-o", str(db), "--append")
    assert code == 0, out
    before = db.read_bytes()
    code, out = run(
        "build-db", *map(str, scans[16:]), "-o", str(db), "--append", "--side-views", "1"
    )
    assert code == 1 and "side-views 3" in out and "Traceback" not in out
    assert db.read_bytes() == before
    from disco_cli.maps.database import Database

    with Database.open(db) as d:
        ids, sigs = d.side_signatures()
        assert d.side_offsets == (3.0, -3.0) and len(d) == 16
        assert np.bincount(ids).tolist()[1:] == [2] * 16
    code, out = run("query", str(scans[5]), "--db", str(db), "--topk", "3", "--format", "jsonl")
    rows = [json.loads(line) for line in out.splitlines()]
    assert code == 0 and rows[0]["match"].endswith(scans[5].name) and rows[0]["match_id"] == 6
    assert [r["match_id"] for r in rows] == sorted(
        set(r["match_id"] for r in rows), key=[r["match_id"] for r in rows].index
    )
    code, out = run("build-db", str(scans[0]), "-o", str(tmp_path / "x.db"), "--side-views", "-1")
    assert code != 0 and "--side-views" in out


def test_a_damaged_side_view_is_skipped_with_one_warning_and_listed_by_check(samples, tmp_path):
    import sqlite3

    db = tmp_path / "map.db"
    scans = list_scans(samples / "00")
    code, out = run("build-db", *map(str, scans[:6]), "-o", str(db), "--side-views", "2")
    assert code == 0, out
    nan = np.full(1024, np.nan, dtype="<f2").tobytes()
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE side_views SET signature = ? WHERE scan_id = 3", (nan,))
    conn.close()
    code, out = run("query", str(scans[0]), "--db", str(db))
    warnings = [ln for ln in out.splitlines() if ln.startswith("warning")]
    assert code == 0 and "Traceback" not in out, out
    assert len(warnings) == 1 and "scan 3 (a side view)" in warnings[0], out
    code, out = run("info", str(db), "--check")
    assert code != 0 and "scan 3" in out and "side view fails its checksum" in out
    assert "damaged scans: 3\n" in out


def test_view_index_grown_one_scan_at_a_time_answers_as_one_built_at_once():
    rng = np.random.default_rng(11)
    n, v, dim = 40, 2, 12
    sigs = rng.normal(size=(n, dim)).astype(np.float32)
    views = rng.normal(size=(n, v, dim)).astype(np.float32)
    whole = ViewIndex(sigs, np.repeat(np.arange(n), v), views.reshape(-1, dim))
    grown = ViewIndex(np.empty((0, dim), np.float32), np.empty(0, np.int64), np.empty((0, dim)))
    for i in range(n):
        grown.append(sigs[i][None], views[i][None])
    q = rng.normal(size=(4, dim)).astype(np.float32)
    for limit in (None, [n, 30, 10, 1]):
        a_rows, a_d = whole.search(q, 6, limit=limit)
        b_rows, b_d = grown.search(q, 6, limit=limit)
        assert a_rows.tolist() == b_rows.tolist()
        np.testing.assert_allclose(a_d, b_d)


def test_loop_detector_with_side_views_closes_a_loop_driven_beside_the_first_pass(samples):
    """A revisit exactly where a side view looks from (scan 2's points re-centred 2.5 m to
    its left) closes with scan 2 at signature distance ~0 only with side views."""
    from disco_cli import LoopDetector
    from disco_cli.errors import DiscoError

    clouds = [read_scan(p) for p in list_scans(samples / "00")[:8]]
    revisit = clouds[2].copy()
    revisit[:, 1] -= 2.5
    found = {}
    for views in (0.0, 2.5):
        det = LoopDetector("spectral", exclude_frames=5, verify=False, side_views=views)
        for c in clouds:
            det.add(c)
        found[views] = det.add(revisit)
    assert found[2.5][0].match_index == 2 and found[2.5][0].distance < 1e-3
    assert found[0.0][0].distance > 100 * max(found[2.5][0].distance, 1e-6)
    det = LoopDetector("spectral", exclude_frames=5, verify=False, side_views=2.5)
    with pytest.raises(DiscoError, match="side views"):
        det.add_embedded(np.zeros(1024, np.float32), np.zeros((40, 120), np.float32))


def test_loop_detector_with_side_views_streams_the_loops_of_disco_loops(samples):
    from disco_cli import LoopDetector

    args = ["--exclude-frames", "5", "--side-views", "2.5", "--format", "jsonl"]
    code, out = run("loops", str(samples / "00"), *args)
    want = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert code == 0 and want
    det = LoopDetector(exclude_frames=5, verify=False, side_views=2.5)
    got = []
    for p in list_scans(samples / "00"):
        got += det.add(read_scan(p), name=str(p))
    assert [(g.query_index, g.match_index) for g in got] == [
        (w["query_index"], w["match_index"]) for w in want
    ]
    for g, w in zip(got, want):
        assert abs(g.distance - w["distance"]) < 1e-5 and abs(g.yaw_deg - w["yaw_deg"]) < 1e-4
