"""Snapping the best match to the map scan nearest the query (search.snap_first): the
rule against hand-placed poses, its place in match_queries (a tie-break of the ranking
score), and end to end on a tiny world where the truth is the map scan nearest each
query's true position."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from query_stubs import StubModel

from disco_cli.errors import DiscoError
from disco_cli.maps.database import MatchRows
from disco_cli.model.interface import Abilities
from disco_cli.query.query_policy import policy_for
from disco_cli.query.search import SignatureIndex, match_queries, snap_first


class _Model(StubModel):
    """Re-ranks by the stored score (feature column 0); its position estimate puts the
    query at `at` in the frame of whichever match it is asked about (feature column 1 is
    that match's row), headed `yaw` from it."""

    abilities = Abilities(rerank=True, refine_yaw=True, locate=True)

    def __init__(self, at=(0.0, 0.0), yaw=30.0, radius=5.0, margin=0.1):
        super().__init__(rerank=4, snap_radius=radius, snap_margin=margin, refine_yaw=1)
        self.at, self.heading = np.asarray(at, np.float64), yaw
        self.asked: list[int] = []  # rows whose position was estimated
        self.refined: list[int] = []  # rows whose yaw was refined

    def query_position_conf(self, query_features, match_features, check_below):
        self.asked.append(int(match_features[1]))
        return self.heading, self.at, float("nan")

    def refine_yaw_conf(self, query_features, match_features, check_below):
        self.refined += [int(f[1]) for f in match_features]
        return np.full(len(match_features), -1.0), np.full(len(match_features), np.nan)


def _stored(poses, scores) -> MatchRows:
    n = len(poses)
    feats = np.c_[np.asarray(scores, np.float64), np.arange(n)]
    return MatchRows(
        np.arange(n), [f"s{i}" for i in range(n)], np.asarray(poses, np.float64), feats
    )


def _snap(model, stored, best=0, radius=5.0, margin=0.1):
    return snap_first(model, None, stored, best, stored.features[:, 0], radius, margin)


def test_the_candidate_nearest_the_estimate_goes_first() -> None:
    # Row 0 (best) sits at (10, 0) headed 90 degrees; the query is 2 m ahead of it, so at
    # (10, 2) on the map. Row 2 is nearest that (0.5 m) and re-ranks within 0.1.
    poses = [
        [10.0, 0.0, 0.0, math.pi / 2],
        [10.0, -1.0, 0.0, 0.0],
        [10.5, 2.0, 0.0, 0.0],
        [10.0, 2.0, 0.0, 0.0],  # at the estimate itself, but re-ranks 0.3 worse
        [np.nan, np.nan, 0.0, 0.0],  # re-ranks well, but where it lies is unknown
    ]
    stored = _stored(poses, [0.40, 0.42, 0.45, 0.70, 0.41])
    model = _Model(at=(2.0, 0.0))
    first, yaw, _ = _snap(model, stored)
    assert first == 2
    # The query heads 90 + 30 = 120 degrees on the map (row 0's heading and the yaw to
    # it); row 2 heads 0 degrees: the yaw to row 2 is 120, with no second search.
    assert yaw == pytest.approx(120.0)
    assert model.asked == [0]


def test_the_yaw_to_the_scan_snapped_to_wraps_and_needs_its_heading() -> None:
    # The query heads 90 + 30 = 120 degrees; row 1 heads -100: the yaw to it is 220,
    # that is -140. Without row 1's heading the yaw is left to be searched for.
    poses = [[10.0, 0.0, 0.0, math.pi / 2], [10.0, 2.0, 0.0, math.radians(-100.0)]]
    first, yaw, _ = _snap(_Model(at=(2.0, 0.0)), _stored(poses, [0.40, 0.42]))
    assert first == 1 and yaw == pytest.approx(-140.0)
    poses[1][3] = np.nan
    first, yaw, _ = _snap(_Model(at=(2.0, 0.0)), _stored(poses, [0.40, 0.42]))
    assert first == 1 and yaw is None


def test_radius_and_margin_bound_the_candidates() -> None:
    poses = [[0.0, 0.0, 0.0, 0.0], [6.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]]
    stored = _stored(poses, [0.50, 0.50, 0.65])
    model = _Model(at=(6.0, 0.0))  # the query is at row 1, 6 m from row 0
    # Row 1 lies beyond the radius, row 2 beyond the margin: the best stays.
    assert _snap(model, stored)[:2] == (0, 30.0)
    # A wider radius lets row 1 in; a wider margin alone lets row 2 in.
    assert _snap(model, stored, radius=6.5)[0] == 1
    assert _snap(model, stored, margin=0.2)[0] == 2


def test_a_best_match_without_a_pose_is_left_alone() -> None:
    stored = _stored([[np.nan] * 4, [1.0, 0.0, 0.0, 0.0]], [0.3, 0.3])
    model = _Model(at=(1.0, 0.0))
    first, yaw, _ = _snap(model, stored, margin=1.0)
    assert first == 0 and yaw is None and model.asked == []


class _Db:
    def __init__(self, poses, scores):
        self.stored = _stored(poses, scores)

    def rows(self, ids):
        ids = np.asarray(ids)
        s = self.stored
        return MatchRows(ids, [s.paths[i] for i in ids], s.poses[ids], s.features[ids])


def _match(model, db, k=2, **options):
    n = len(db.stored.ids)
    (found,) = match_queries(
        SignatureIndex(np.arange(n, dtype=np.float32)[:, None]),
        np.arange(n),
        db,
        model,
        np.zeros((1, 1), np.float32),
        np.zeros((1, 2)),
        k,
        policy_for(model, **options),
    )
    return found


def test_match_queries_snaps_and_carries_the_yaw_to_the_new_first() -> None:
    # Rows 0-3 along the x axis, 1 m apart, headed 0; row 1 re-ranks best, but the query
    # is 1.8 m ahead of it: row 3 (0.2 m away, re-ranking 0.05 worse) goes first. Its
    # yaw is the one estimated with row 1 (30 degrees) carried over by the two poses,
    # which head alike: 30, with no second search.
    poses = [[x, 0.0, 0.0, 0.0] for x in range(4)]
    db = _Db(poses, [0.50, 0.40, 0.60, 0.45])
    model = _Model(at=(1.8, 0.0))
    found = _match(model, db)
    assert [m.row for m in found] == [3, 1]
    # The tie-break: row 3 takes row 1's distance (0.40, not its own 0.45), so the two
    # show the same and the rows stay sorted.
    assert [m.distance for m in found] == pytest.approx([0.40, 0.40])
    assert model.asked == [1] and model.refined == []
    assert [m.yaw_deg for m in found] == [30.0, 0.0]


def test_match_queries_reuses_the_yaw_when_the_best_stays() -> None:
    poses = [[x, 0.0, 0.0, 0.0] for x in range(4)]
    db = _Db(poses, [0.50, 0.40, 0.60, 0.45])
    model = _Model(at=(0.2, 0.0))  # the query is at row 1 itself
    found = _match(model, db)
    assert [m.row for m in found] == [1, 3]
    assert [m.distance for m in found] == pytest.approx([0.40, 0.45])
    assert model.asked == [1] and model.refined == []  # no second estimate
    assert found[0].yaw_deg == 30.0
    # --snap-radius 0: no estimate at all, the refined yaw as before.
    model = _Model(at=(1.8, 0.0))
    assert [m.row for m in _match(model, db, snap_radius=0)] == [1, 3]
    assert model.asked == [] and model.refined == [1]
    # --rerank 0: the signature order, never snapped.
    model = _Model(at=(1.8, 0.0))
    assert [m.row for m in _match(model, db, rerank=0)] == [0, 1] and model.asked == []


def test_snap_radius_checks() -> None:
    assert policy_for(_Model(), snap_radius=2.5).snap_radius == 2.5
    assert policy_for(StubModel(), snap_radius=0).snap_radius == 0.0  # asks for nothing
    with pytest.raises(DiscoError, match="stub cannot estimate the query's position"):
        policy_for(StubModel(), snap_radius=5)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(DiscoError, match="snap radius"):
            policy_for(_Model(), snap_radius=bad)


# --- end to end ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def offset_world(tmp_path_factory) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """A map scan every 2 m along y = 0; queries driven back 2 m and 4 m to the side,
    0.5 m past a map scan: the nearest map scan is one, the next 0.25-0.44 m farther."""
    pytest.importorskip("disco_cli.model.bev")
    from test_eval_cli import run, world_points, write_session

    root = tmp_path_factory.mktemp("offset")
    rng = np.random.default_rng(7)
    world = world_points(rng)
    maps = [(x, 0.0, 0.0) for x in np.arange(0.0, 61.0, 2.0)]
    queries = [(x + 0.5, lat, np.pi) for lat in (2.0, 4.0) for x in np.arange(4.0, 58.0, 4.0)]
    write_session(root / "00", world, maps, rng)
    write_session(root / "01", world, queries, rng)
    db = root / "map.db"
    result = run("build-db", root / "00", "-o", db)
    assert result.exit_code == 0, result.output
    return root, db, np.array(maps)[:, :2], np.array(queries)[:, :2]


def test_query_snaps_to_the_map_scan_nearest_the_query(offset_world) -> None:
    from test_eval_cli import run

    root, db, map_xy, query_xy = offset_world
    result = run("query", root / "01", "--db", db, "--topk", "1", "--format", "jsonl")
    assert result.exit_code == 0, result.output
    picked = [int(Path(json.loads(ln)["match"]).stem) for ln in result.stdout.splitlines()]
    nearest = [int(np.argmin(np.hypot(*(map_xy - q).T))) for q in query_xy]
    assert picked == nearest


def test_snap_radius_reaches_the_report_and_is_checked(offset_world, tmp_path) -> None:
    from test_eval_cli import run

    root, db, _, _ = offset_world
    for option, want in ((None, {"radius_m": 5.0, "margin": 0.1}), ("0", None), ("2.5", 2.5)):
        out = tmp_path / f"report-{option}"
        extra = [] if option is None else ["--snap-radius", option]
        result = run("eval", root / "01", "--db", db, "--report", out, *extra)
        assert result.exit_code == 0, result.output
        got = json.loads((out / "metrics.json").read_text())["run"].get("snap")
        assert (got if not isinstance(want, float) else got["radius_m"]) == want, option
    result = run("query", root / "01", "--db", db, "--snap-radius", "-1")
    assert result.exit_code == 2  # typer's usage error, like the other bounded options
    spectral = tmp_path / "spectral.db"
    assert run("build-db", root / "00", "-o", spectral, "--model", "spectral").exit_code == 0
    result = run("query", root / "01", "--db", spectral, "--snap-radius", "5")
    assert result.exit_code == 1
    assert "spectral cannot estimate the query's position" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_map_query_snap_radius(offset_world) -> None:
    """The Python API's `snap_radius` does what `--snap-radius` does: by default each
    query's first match is the map scan nearest it; 0 gives the CLI's --snap-radius 0
    order; a negative radius is one clear error."""
    from test_eval_cli import run

    from disco_cli.io.readers import read_scan
    from disco_cli.maps.facade import Map

    root, db, map_xy, query_xy = offset_world
    scans = sorted((root / "01" / "velodyne").glob("*.bin"))
    result = run(
        "query", root / "01", "--db", db, "--topk", "1", "--format", "jsonl", "--snap-radius", "0"
    )
    assert result.exit_code == 0, result.output
    cli_off = [int(Path(json.loads(ln)["match"]).stem) for ln in result.stdout.splitlines()]
    with Map.open(db) as m:
        for scan, q, off in zip(scans, query_xy, cli_off):
            points = read_scan(scan)
            (first,) = m.query(points, topk=1)
            assert int(Path(first.name).stem) == int(np.argmin(np.hypot(*(map_xy - q).T)))
            (first,) = m.query(points, topk=1, snap_radius=0)
            assert int(Path(first.name).stem) == off
        with pytest.raises(DiscoError, match="snap radius"):
            m.query(read_scan(scans[0]), snap_radius=-1)
