"""Rows come sorted by the distance they show (issue 32): one score ranks them and is
their `distance`, for every query of a simulated world, and `max_distance` cuts by it
before the top k are taken."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from disco_cli.io.readers import list_scans, read_scan


@pytest.fixture(scope="module")
def sample_map(samples: Path, tmp_path_factory: pytest.TempPathFactory):
    """The shipped model's map of the sample town's session 00 (with poses, so the snap
    runs), and session 01's scans as queries."""
    from disco_cli import Map
    from disco_cli.io.poses import read_kitti_poses

    paths = list_scans(samples / "00")
    poses = read_kitti_poses(samples / "00" / "poses.txt")
    path = tmp_path_factory.mktemp("order") / "map.db"
    with Map.create(path, "default") as m:
        m.add_many((read_scan(p), str(p), T) for p, T in zip(paths, poses))
    return path, [read_scan(p) for p in list_scans(samples / "01")]


def test_every_query_s_rows_are_sorted_by_their_distance(sample_map) -> None:
    from disco_cli import Map

    path, queries = sample_map
    with Map.open(path) as m:
        wide = replace(m.model.query_policy, rerank_candidates=20)  # many re-ranked rows
        for policy in (m.model.query_policy, wide):
            for i, points in enumerate(queries):
                d = [r.distance for r in m.query(points, topk=10, policy=policy)]
                assert len(d) == 10 and all(np.isfinite(d)), i
                assert all(a <= b for a, b in zip(d, d[1:])), (i, np.round(d, 4))


def test_max_distance_cuts_by_the_shown_distance_before_the_top_k(sample_map) -> None:
    from disco_cli import Map

    path, queries = sample_map
    with Map.open(path) as m:
        for points in queries[::5]:
            full = m.query(points, topk=10)
            for j in (0, 4, 9):
                bound = full[j].distance
                kept = [r for r in full if r.distance <= bound]
                # Asked for 3 within the bound: the first 3 of those within it.
                got = m.query(points, topk=3, max_distance=bound)
                assert [r.name for r in got] == [r.name for r in kept[:3]]
                assert all(r.distance <= bound for r in got)
            below = m.query(points, topk=10, max_distance=full[0].distance - 1e-6)
            assert below == []


def test_disco_serve_answers_under_the_policy_it_was_given(sample_map, samples: Path) -> None:
    """`ServeOptions.policy` reaches every request: with re-ranking off the rows are the
    plain signature order (the map's nearest signatures), sorted by what they show."""
    from disco_cli import Map
    from disco_cli.embedding.load import load_bev
    from disco_cli.service.serve import QueryService, ServeOptions

    path, _ = sample_map
    scan = str(list_scans(samples / "01")[3])
    with Map.open(path) as m:
        ids, sigs = m.database.signatures()
        query_sig, _ = m.model.embed(load_bev(scan, m.model.bev_config)[None])
        nearest = ids[np.argsort(np.linalg.norm(sigs - query_sig[0], axis=1), kind="stable")[:5]]
        plain = replace(m.model.query_policy, rerank_candidates=0)
        served = {}
        for name, policy in (("shipped", None), ("plain", plain)):
            service = QueryService(m, ServeOptions(topk=5, policy=policy, scan_root=samples))
            served[name] = service.handle({"scan": scan})["rows"]
    assert [r["match_id"] for r in served["plain"]] == nearest.tolist()
    assert served["shipped"] != served["plain"]  # the shipped policy re-ranks
    for rows in served.values():
        d = [r["distance"] for r in rows]
        assert d == sorted(d)
