"""One confidence per answer, a bounded distance, and loops a back end can trust.

Truths: the simulator's poses (a loop is true where the two scans stand within a few
metres), a map with and without the query's own scan (the other rows must not move),
and a held-back selection world's rows, which the shipped calibration never saw (the
observed share of true rows per confidence bin must match the predicted).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.io.poses import read_kitti_poses
from disco_cli.io.readers import list_scans, read_scan
from disco_cli.maps.facade import Map

TRUE_WITHIN_M = 5.0  # the samples' scans are 12 m apart; a revisit passes 2.4 m away


def run(*args: object) -> tuple[int, str, str]:
    res = CliRunner().invoke(app, [str(a) for a in args])
    if res.exception and not isinstance(res.exception, SystemExit):
        raise res.exception
    return res.exit_code, res.stdout, res.stderr


def _xy(folder: Path) -> np.ndarray:
    return read_kitti_poses(folder / "poses.txt")[:, :2, 3]


@pytest.fixture(scope="module")
def two_maps(samples: Path, tmp_path_factory: pytest.TempPathFactory):
    """Maps of session 00, without and with session 01's scan 5 (the query) in them."""
    tmp = tmp_path_factory.mktemp("own")
    query = str(list_scans(samples / "01")[5])
    scans = [str(p) for p in list_scans(samples / "00")]
    out = []
    for name, extra in (("without.db", []), ("with.db", [query])):
        m = Map.create(tmp / name, "default")
        m.add_files(scans + extra)
        m.close()
        out.append(tmp / name)
    return query, out[0], out[1]


def test_the_query_s_own_scan_leaves_the_other_rows_distances(two_maps, samples: Path) -> None:
    query, without, with_own = two_maps
    pts = read_scan(query)
    with Map.open(without) as m:
        before = {r.name: r.distance for r in m.query(pts, topk=5)}
    with Map.open(with_own) as m:
        after = m.query(pts, topk=6)
    # The copy comes first, with a bounded distance (its re-rank distance, about 0).
    assert after[0].name == query
    assert 0.0 <= after[0].distance < 0.01
    # The true revisit (the map scan nearest the query by the simulator's poses) keeps
    # its distance, and so does every other row.
    q_xy = _xy(samples / "01")[5]
    names = [str(p) for p in list_scans(samples / "00")]
    true = names[int(np.argmin(np.hypot(*(_xy(samples / "00") - q_xy).T)))]
    assert true in before
    rest = {r.name: r.distance for r in after[1:]}
    assert rest[true] == pytest.approx(before[true], abs=1e-6)
    for name, d in before.items():
        assert rest[name] == pytest.approx(d, abs=1e-6), name
    # Rows stay sorted by the distance they show.
    shown = [r.distance for r in after]
    assert shown == sorted(shown)


def test_max_distance_keeps_the_true_match_beside_the_own_scan(two_maps, samples: Path) -> None:
    query, without, with_own = two_maps
    with Map.open(without) as m:
        first = m.query(read_scan(query), topk=1)[0]
    cut = f"{first.distance + 1e-6:.7f}"
    code, out, err = run("query", query, "-d", with_own, "--max-distance", cut, "--format", "jsonl")
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    matched = [Path(r["match"]).resolve() for r in rows]
    assert Path(query).resolve() in matched and Path(first.name).resolve() in matched


def test_every_row_carries_its_confidence_in_the_unit_interval(two_maps) -> None:
    query, without, _ = two_maps
    with Map.open(without) as m:
        rows = m.query(read_scan(query), topk=5)
        cheap = replace(m.model.query_policy, check_candidates=0)
        fast = m.query(read_scan(query), topk=5, policy=cheap)
    for r in rows + fast:
        assert r.confidence is not None and 0.0 <= r.confidence <= 1.0
    # The check ran on the best rows only; the cheaper path checks none.
    assert [r.verified for r in rows[:1]] == [True]
    assert not any(r.verified for r in fast)


def _loops(folder: Path, *args: str) -> list[dict]:
    code, out, err = run("loops", folder, "--exclude-frames", "5", "--format", "jsonl", *args)
    assert code == 0, err
    return [json.loads(line) for line in out.splitlines()]


def test_default_loops_are_all_true(samples: Path) -> None:
    xy = _xy(samples / "00")
    found = _loops(samples / "00")
    assert found, "the revisits of data/samples/00 (scans 20-25) gave no loop"
    for lp in found:
        d = float(np.hypot(*(xy[lp["query_index"]] - xy[lp["match_index"]])))
        assert d <= TRUE_WITHIN_M, lp
        assert lp["confidence"] >= 0.9
    # --all reports every scan's best candidate, the false ones included.
    every = _loops(samples / "00", "--all")
    assert len(every) > len(found)


def test_default_loops_report_none_without_a_revisit(samples: Path, tmp_path: Path) -> None:
    # The first lap of session 00 (scans 0-19): no place is passed twice.
    seq = tmp_path / "lap" / "velodyne"
    seq.mkdir(parents=True)
    for p in list_scans(samples / "00")[:20]:
        shutil.copy(p, seq / p.name)
    assert _loops(tmp_path / "lap") == []
    assert _loops(tmp_path / "lap", "--all")  # there were candidates to refuse


def test_the_help_states_the_default_that_the_detector_applies() -> None:
    from disco_cli.commands.options import DEFAULT_MIN_CONFIDENCE
    from disco_cli.query.loop_detector import LOOP_MIN_CONFIDENCE

    assert DEFAULT_MIN_CONFIDENCE == LOOP_MIN_CONFIDENCE
    code, out, _ = run("loops", "--help")
    assert code == 0 and f"default {LOOP_MIN_CONFIDENCE}" in " ".join(out.split())


def test_disco_eval_scores_the_rows_disco_query_prints(samples: Path, tmp_path: Path) -> None:
    db = tmp_path / "map.db"
    assert run("build-db", samples / "00", "-o", db, "-q")[0] == 0
    code, out, err = run("query", samples / "01", "-d", db, "-k", "1", "--format", "jsonl")
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    code, out, err = run("eval", samples / "01", "-d", db, "--format", "jsonl", "-q")
    assert code == 0, err
    metrics = json.loads(out.splitlines()[-1])
    # The truth by hand, from the rows disco query printed: a top 1 within 3 m of the
    # query's pose (eval's default radius) is right.
    map_xy, q_xy = _xy(samples / "00"), _xy(samples / "01")
    names = [str(p.resolve()) for p in list_scans(samples / "00")]
    right, has, conf = [], [], []
    for i, r in enumerate(rows):
        d = np.hypot(*(map_xy - q_xy[i]).T)
        has.append(bool(d.min() <= 3.0))
        right.append(bool(d[names.index(str(Path(r["match"]).resolve()))] <= 3.0))
        conf.append(r["confidence"])
    assert metrics["num_queries_with_match"] == sum(has)
    assert metrics["num_correct_top1"] == sum(a and b for a, b in zip(right, has))
    # Recall at 100 % precision over the confidence, from the same rows.
    order = np.argsort(-np.array(conf), kind="stable")
    ok = np.array(right)[order] & np.array(has)[order]
    cut = len(ok) if ok.all() else int(np.argmin(ok))
    ranked = np.array(conf)[order]
    while 0 < cut < len(ok) and ranked[cut - 1] == ranked[cut]:
        cut -= 1  # rows of one confidence are accepted together
    want = ok[:cut].sum() / sum(has)
    assert metrics["recall@100%precision_by_confidence"] == pytest.approx(want)


def test_the_shipped_calibration_holds_on_a_held_back_selection_world() -> None:
    # mulran-8623's best 3 rows of every query, with their cues and whether each is a
    # true revisit (within 3 m of the query's true position): a world the fit never saw
    # (benchmarks/calibrate_confidence.py writes the file; HELD_BACK there).
    import gzip

    from disco_cli.query.confidence import PlaceCues, calibrations, checked_confidence
    from disco_cli.query.relative_pose import LayoutCheck

    data = json.loads(
        gzip.open(Path(__file__).parent / "data" / "confidence_held_back.json.gz").read()
    )
    fitted = {key[0] for key in calibrations()}
    assert len(fitted) == 1

    class Shipped:  # the model the calibration is for, by its fingerprint
        fingerprint = next(iter(fitted))

    predicted, observed = [], []
    for r in data["rows"]:
        cues = PlaceCues(r["distance"], r["rerank"], r["rerank_own"], r["signature"], r["lead"])
        layout = LayoutCheck(r["peak"], r["shift_m"], r["flipped"])
        predicted.append(checked_confidence(Shipped(), cues, r["yaw_conf"], layout))
        observed.append(r["true"])
    p, y = np.array(predicted), np.array(observed, float)
    assert len(p) > 2000 and np.isfinite(p).all() and ((p >= 0) & (p <= 1)).all()
    # Per bin of at least 100 rows, the observed share of true rows lies within 0.1 of
    # the mean predicted confidence (stated tolerance; measured: 0.08 at most).
    edges = [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 1.0 + 1e-9]
    bins = 0
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (p >= lo) & (p < hi)
        if sel.sum() >= 100:
            bins += 1
            assert abs(y[sel].mean() - p[sel].mean()) <= 0.1, (lo, hi, y[sel].mean(), p[sel].mean())
    assert bins >= 6
    # And it ranks: the confident rows are right (99 % above 0.9).
    assert y[p >= 0.9].mean() >= 0.97
