"""The simulator's boulevard style and the later robots' offsets in every direction
(issue 24): what was asked is what the worlds hold, and the poses are the scans' own."""

from __future__ import annotations

import json

import numpy as np
import pytest

from disco_cli.io.poses import read_kitti_poses
from disco_cli.simulator import (
    ChangeParams,
    RobotParams,
    Town,
    TownParams,
    get_sensor,
    plan_sessions,
    simulate,
)
from disco_cli.simulator.session import _scan_seed, cast, finish_scan
from disco_cli.simulator.styles import BOULEVARD_TOWN, boulevard_change

BLV = {k: tuple(v) if isinstance(v, tuple) else v for k, v in BOULEVARD_TOWN.items()}


def _objects(town: Town, cls: str) -> list[np.ndarray]:
    obj = np.array(town.static.obj)
    rows = np.array(town.static.rows)
    return [rows[obj == i] for i, c in enumerate(town.objects) if c == cls and (obj == i).any()]


def _across(town: Town, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance from the nearest street's centre line, which street) of points [M, 2],
    counting only streets the point lies alongside."""
    best = np.full(len(xy), np.inf)
    which = np.full(len(xy), -1)
    for k, s in enumerate(town.streets):
        rel = xy - s.a
        along, across = rel @ s.dir, np.abs(rel @ s.left)
        ok = (along > 0) & (along < s.length) & (across < best)
        best[ok], which[ok] = across[ok], k
    return best, which


def test_boulevard_is_alike_on_both_sides_at_the_distances_asked():
    town = Town(3, TownParams(**BLV))
    # Nearest faces of the buildings: 11-24 m from the centre line, plain single boxes.
    fronts, heights = [], {}
    for b in _objects(town, "buildings"):
        box = b[0]
        centre, hy = box[1:3], min(box[4], box[5])
        d, k = _across(town, centre[None])
        if k[0] < 0 or d[0] > 40:
            continue  # the outskirts' sheds
        fronts.append(d[0] - hy)
        s = town.streets[k[0]]
        side = np.sign((centre - s.a) @ s.left)
        heights.setdefault((k[0], side), []).append(2 * box[6] - 0.3)
    fronts = np.array(fronts)
    assert len(fronts) > 60
    assert np.percentile(fronts, 5) >= 10.5 and np.percentile(fronts, 95) <= 24.5
    # Both sides of a street: one building height (each within 1 m of it).
    pairs = [
        (np.median(v), np.median(heights[(k, -side)]))
        for (k, side), v in heights.items()
        if side > 0 and (k, -side) in heights
    ]
    assert len(pairs) >= 8
    assert all(abs(a - b) <= 2.0 + 1e-9 for a, b in pairs)
    # Hedges and walls (walls count with the fences) at 6.5-8 m, trees at 4.5-9 m.
    for cls in ("hedges", "fences"):
        d = np.array([_across(town, o[:1, 1:3])[0][0] for o in _objects(town, cls)])
        d = d[np.isfinite(d)]
        assert len(d) > 20 and np.all((d >= 6.3) & (d <= 8.2)), cls
    trees = np.array([_across(town, o[:1, 1:3])[0][0] for o in _objects(town, "trees")])
    # (The blocks' own trees keep 3 m off the sidewalk: 10 m or more from the centre.)
    street_trees = trees[trees < 9.5]
    assert len(street_trees) > 200 and np.all(street_trees >= 4.5)
    # Parked cars' spots at 3-4 m from the centre line; nothing else along the street.
    spots = np.array([_across(town, c[None])[0][0] for c, _, _ in town._parking])
    assert len(spots) > 100 and np.all((spots >= 3.0) & (spots <= 4.2))
    assert "furniture" not in town.objects


def test_boulevard_change_removes_what_was_asked():
    town = Town(3, TownParams(**BLV, change=ChangeParams(**boulevard_change(0.25))))
    acts = town.session_changes(1)
    classes = np.array(town.objects)
    present = town._pool().present0
    # Removed: half of the parked cars, hedges and walls; changed: a quarter of the trees.
    for cls, verb, want in (
        ("cars", "gone", 0.5),
        ("hedges", "cut down", 0.5),
        ("fences", "taken down", 0.5),
        ("trees", None, 0.25),
    ):
        ids = np.flatnonzero((classes == cls) & present)
        n = len(ids)
        hit = sum(1 for o in ids if o in acts and (verb is None or acts[o] == verb))
        assert n >= 40, cls
        assert abs(hit / n - want) <= 4 * np.sqrt(want * (1 - want) / n), (cls, hit, n)


def test_query_scans_jitter_along_and_across_as_asked():
    town = Town(3, TownParams(**BLV))
    sensor = get_sensor("vlp16")
    plain = plan_sessions(town, sensor, 2, 300, 4.0, 3, RobotParams(offset_m=0.0))
    moved = plan_sessions(town, sensor, 2, 300, 4.0, 3, RobotParams(offset_m=0.0, jitter_m=3.0))
    np.testing.assert_array_equal(plain[0].poses, moved[0].poses)  # the map stays
    a, b = plain[1].poses, moved[1].poses
    # The displacement in the unjittered pose's frame: along (x) and across (y).
    d = np.einsum("nji,nj->ni", a[:, :3, :3], b[:, :3, 3] - a[:, :3, 3])[:, :2]
    straight = (
        np.abs(np.degrees(np.arctan2(b[:, 1, 0], b[:, 0, 0]) - np.arctan2(a[:, 1, 0], a[:, 0, 0])))
        % 360
        < 1.0
    )
    d = d[straight]  # on a curve the along-jitter also turns the car
    assert len(d) > 200
    assert np.all(np.abs(d) <= 3.0 + 0.05)
    # Uniform in +-3 m: standard deviation 3 / sqrt(3), within 15 %.
    np.testing.assert_allclose(d.std(axis=0), 3 / np.sqrt(3), rtol=0.15)
    assert np.abs(d.mean(axis=0)).max() < 0.35


def test_revisits_to_the_side_as_asked():
    params = TownParams(**{**BLV, "road_width_m": (19.0, 22.0)})
    town = Town(4, params)
    sensor = get_sensor("hdl32")
    on_line = plan_sessions(town, sensor, 4, 150, 4.0, 4, RobotParams(offset_m=0.0))
    aside = plan_sessions(town, sensor, 4, 150, 4.0, 4, RobotParams(side_m=(4.0, 8.0)))
    np.testing.assert_array_equal(on_line[0].poses, aside[0].poses)
    for k in (1, 2, 3):
        a, b = on_line[k].poses, aside[k].poses
        # Session k's scans against the same scans driven on session 00's line (along
        # the street they part after a corner: an offset line is longer or shorter).
        d = np.einsum("nji,nj->ni", a[:, :3, :3], b[:, :3, 3] - a[:, :3, 3])[:, :2]
        turn = np.degrees(np.arctan2(b[:, 1, 0], b[:, 0, 0]) - np.arctan2(a[:, 1, 0], a[:, 0, 0]))
        d = d[np.abs((turn + 180) % 360 - 180) < 0.5]  # straight stretches
        assert len(d) > 60
        across = np.abs(d[:, 1])
        assert np.all((across >= 4.0 - 0.02) & (across <= 8.0 + 0.02)), (k, across.min())
        assert np.all(np.sign(d[:, 1]) == np.sign(d[0, 1]))  # one side per session
        # Uniform in 4..8 m: standard deviation 4 / sqrt(12), within 20 %.
        assert abs(across.std() - 4 / np.sqrt(12)) < 0.2 * 4 / np.sqrt(12)
        # Inside the road (half width at least 9.5 m).
        assert np.all(np.abs(aside[k].offset_m) + 4.0 < 9.5)
    with pytest.raises(Exception, match="robot-offset or --robot-side"):
        RobotParams(offset_m=1.0, side_m=(4.0, 8.0)).check()


def test_jittered_scans_are_cast_from_their_written_pose(tmp_path):
    params = TownParams(**BLV, change=ChangeParams(**boulevard_change(0.25)))
    robot = RobotParams(offset_m=0.0, jitter_m=3.0, sensor="vlp16")
    meta = simulate(
        tmp_path,
        sessions=2,
        frames=3,
        step_m=4.0,
        sensor="hdl32",
        seed=6,
        params=params,
        robot=robot,
        threads=1,
    )
    assert "--robot-jitter 3" in meta["command"]
    town = Town(6, params)
    world = town.session_world(1)
    poses = read_kitti_poses(tmp_path / "01" / "poses.txt")
    times = np.loadtxt(tmp_path / "01" / "times.txt")
    sensor = get_sensor("vlp16")
    plan = plan_sessions(town, get_sensor("hdl32"), 2, 3, 4.0, 6, robot)[1].poses
    # poses.txt holds the jittered poses (to its text precision)...
    np.testing.assert_allclose(poses, plan, atol=1e-6)
    for i in range(3):
        # ...and each scan is cast from that pose: cast again, the same bytes.
        w = world.at(float(times[i]), plan[i, :2, 3])
        ranges, ids, cosi = cast(w, plan[i], sensor, np.array([_scan_seed(6, 1, i)], np.uint64))
        rng = np.random.default_rng([6, 9, 1, i])
        pts = finish_scan(
            rng, sensor, sensor.directions(), plan[i], ranges[0], ids[0], cosi[0], w, town
        )
        assert pts.tobytes() == (tmp_path / "01" / "velodyne" / f"{i:06d}.bin").read_bytes()
    assert json.loads((tmp_path / "world.json").read_text())["robot"]["jitter_m"] == 3.0
