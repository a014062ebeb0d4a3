"""The simulator's change model, town styles, terrain and later sessions' robots.

Changes are measured on the geometry itself: an object counts as changed when its
primitive rows in a later session differ from session 00's (or are gone).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.errors import DiscoError
from disco_cli.io.poses import read_kitti_poses
from disco_cli.simulator import (
    ChangeParams,
    RobotParams,
    Town,
    TownParams,
    get_sensor,
    plan_sessions,
    scan,
    simulate,
)
from disco_cli.simulator.objects import BOX, ELLIPSOID
from disco_cli.simulator.params import CHANGE_CLASSES

SMALL = dict(blocks_x=2, blocks_y=2, outskirts_m=30.0)
CLASSES = CHANGE_CLASSES


def changed_share(town: Town, w0, w1, cls: str) -> tuple[int, int]:
    """(objects of class `cls` in session 00, how many of them differ in `w1`)."""
    ids = np.flatnonzero(np.array(town.objects) == cls)
    n = changed = 0
    for o in ids:
        a = w0.table[w0.objects == o]
        if len(a) == 0:
            continue
        n += 1
        b = w1.table[w1.objects == o]
        changed += a.shape != b.shape or not np.array_equal(a, b)
    return n, changed


def test_change_zero_sessions_see_one_static_world():
    town = Town(4, TownParams(**SMALL, change=ChangeParams(0.0)))
    w0, w1, w2 = (town.session_world(k) for k in range(3))
    np.testing.assert_array_equal(w0.table, w1.table)
    np.testing.assert_array_equal(w0.table, w2.table)
    np.testing.assert_array_equal(w0.reflectivity, w1.reflectivity)
    assert len(set(w0.objects.tolist()) - {-1}) > 100  # objects there are
    # Identical scans from one pose (movers left out: they belong to a session's time).
    pose = plan_sessions(town, get_sensor("vlp16"), 1, 5, 3.0, 4)[0].poses[2]
    a = scan(w0, pose, "vlp16", seed=9, town=town)
    b = scan(w1, pose, "vlp16", seed=9, town=town)
    assert len(a) > 10_000 and a.tobytes() == b.tobytes()
    # Within a session, cars, cyclists and people still move, differently per session.
    assert w0.movers is not None and set(w0.movers[:, 9]) == {0.0, 1.0, 2.0}
    assert not np.array_equal(w0.movers, w1.movers)


@pytest.mark.parametrize("fraction", [0.3])
def test_change_fraction_per_class_is_what_was_asked(fraction):
    # A bigger town, so that each class has enough objects to measure a share.
    town = Town(7, TownParams(blocks_x=3, blocks_y=3, change=ChangeParams(fraction)))
    w0 = town.session_world(0)
    for session in (1, 2):
        w1 = town.session_world(session)
        for cls in CLASSES:
            n, changed = changed_share(town, w0, w1, cls)
            want = fraction / 5 if cls == "buildings" else fraction
            if n < 20:
                continue
            # Four binomial standard deviations.
            tol = 4 * np.sqrt(want * (1 - want) / n)
            assert abs(changed / n - want) <= tol, (cls, session, n, changed)
    # Enough classes were measured for the test to mean something.
    sizes = {c: changed_share(town, w0, w0, c)[0] for c in CLASSES}
    assert sum(n >= 20 for n in sizes.values()) >= 5, sizes
    # About as many things come as go: parked cars stay within 20 % of their number.
    cars0 = sizes["cars"]
    cars1 = len(
        set(town.session_world(1).objects.tolist())
        & set(np.flatnonzero(np.array(town.objects) == "cars").tolist())
    )
    assert abs(cars1 - cars0) <= 0.2 * cars0


def test_changes_are_of_their_class_kind():
    town = Town(7, TownParams(blocks_x=3, blocks_y=3, change=ChangeParams(0.5)))
    w0, w1 = town.session_world(0), town.session_world(1)
    acts = town.session_changes(1)
    seen = set()
    for o, action in acts.items():
        a, b = w0.table[w0.objects == o], w1.table[w1.objects == o]
        seen.add(action)
        if action == "new":
            assert len(a) == 0 and len(b) > 0
        elif action in ("gone", "felled", "cut down", "taken down", "demolished"):
            assert len(a) > 0 and len(b) == 0
        elif action in ("grown", "shrunk"):
            crown = (a[:, 0] == ELLIPSOID) & (a[:, 8] < 1)
            ratio = b[crown, 4] / a[crown, 4]
            assert np.ptp(ratio) < 1e-9
            assert (1.15 <= ratio[0] <= 1.4) if action == "grown" else (0.6 <= ratio[0] <= 0.85)
            # The crown keeps its bottom; the trunk stays.
            np.testing.assert_allclose(b[crown, 3] - b[crown, 6], a[crown, 3] - a[crown, 6])
            np.testing.assert_array_equal(b[~crown], a[~crown])
        elif action == "bare":
            crown = (a[:, 0] == ELLIPSOID) & (a[:, 8] < 1)
            assert np.all(b[crown, 8] < 0.41 * a[crown, 8])
            np.testing.assert_array_equal(b[:, :8], a[:, :8])
        elif action == "moved":
            d = np.hypot(*(b[:, 1:3] - a[:, 1:3]).T)
            assert np.ptp(d) < 1e-9 and 1.0 <= d[0] <= 3.0
        elif action == "trimmed":
            # Lower, standing on the same ground.
            assert np.all(b[:, 6] < a[:, 6])
            np.testing.assert_allclose(b[:, 3] - b[:, 6], a[:, 3] - a[:, 6])
        elif action == "other car":
            assert a.shape != b.shape or not np.array_equal(a, b)
            assert np.all(b[:, 0] == BOX) and np.hypot(*(b[0, 1:3] - a[0, 1:3])) < 2.5
    assert {"new", "gone", "felled", "grown", "bare", "moved", "other car"} <= seen


def test_per_class_shares_from_the_town_toml(tmp_path):
    (tmp_path / "town.toml").write_text(
        "[town]\nblocks_x = 3\nblocks_y = 3\n\n[change]\nfraction = 0.1\ncars = 0.8\n"
        "buildings = 0.5\n"
    )
    params = TownParams.load(tmp_path / "town.toml")
    assert params.change == ChangeParams(fraction=0.1, cars=0.8, buildings=0.5)
    assert params.change.rate("trees") == 0.1 and params.change.rate("cars") == 0.8
    town = Town(7, params)
    w0, w1 = town.session_world(0), town.session_world(1)
    for cls, want in (("cars", 0.8), ("trees", 0.1), ("buildings", 0.5)):
        n, changed = changed_share(town, w0, w1, cls)
        assert n >= 30 and abs(changed / n - want) <= 4 * np.sqrt(want * (1 - want) / n), cls
    # Unknown keys and bad values: one line naming the file.
    for text, what in (
        ("[change]\nfraction = 0.2\nparked = 1\n", "unknown change parameters: parked"),
        ("[change]\nfraction = 1.5\n", "within 0..1"),
        ("[change]\ncars = 'many'\n", "not a number"),
        ("[town]\nblocks_x = 2\n[chnage]\nfraction = 0.2\n", "chnage"),
        ("style = 'medieval'\n", "style must be one of"),
    ):
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(DiscoError, match=what) as info:
            TownParams.load(tmp_path / "bad.toml")
        assert "bad.toml" in str(info.value)


def test_ground_truth_poses_do_not_depend_on_the_change(tmp_path):
    kw = dict(sessions=2, frames=4, step_m=6.0, sensor="vlp16", seed=3, threads=1)
    simulate(tmp_path / "classic", params=TownParams(**SMALL), **kw)
    for f in (0.0, 0.3):
        simulate(tmp_path / f"c{f}", params=TownParams(**SMALL, change=ChangeParams(f)), **kw)
    for s in ("00", "01"):
        ref = (tmp_path / "classic" / s / "poses.txt").read_bytes()
        for f in (0.0, 0.3):
            assert (tmp_path / f"c{f}" / s / "poses.txt").read_bytes() == ref
    # The worlds do differ: session 01's scans under change are not those at change 0.
    a = np.fromfile(tmp_path / "c0.0/01/velodyne/000001.bin", np.float32)
    b = np.fromfile(tmp_path / "c0.3/01/velodyne/000001.bin", np.float32)
    assert a.shape != b.shape or not np.array_equal(a, b)
    meta = json.loads((tmp_path / "c0.3/world.json").read_text())
    assert meta["town"]["params"]["change"]["fraction"] == 0.3
    assert "--town OUT/world.json" in meta["command"]  # the small town is in world.json


def test_cli_change_and_style_and_rerun_from_the_command(tmp_path):
    runner = CliRunner()
    args = ["--sessions", "2", "--frames", "2", "--step-m", "5", "--sensor", "vlp16"]
    args += ["--seed", "2", "--change", "0.25", "--style", "park"]
    res = runner.invoke(app, ["simulate", str(tmp_path / "a"), *args])
    assert res.exit_code == 0, res.output
    meta = json.loads((tmp_path / "a/world.json").read_text())
    assert meta["town"]["params"]["style"] == "park"
    # The recorded command writes the same bytes again.
    again = meta["command"].split()[3:]
    res = runner.invoke(app, ["simulate", str(tmp_path / "b"), *again])
    assert res.exit_code == 0, res.output
    for f in ("01/velodyne/000001.bin", "01/poses.txt", "world.json"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    res = runner.invoke(app, ["simulate", str(tmp_path / "c"), "--change", "1.5"])
    assert res.exit_code != 0 and "Traceback" not in res.output


def _objects(town: Town, cls: str) -> list[np.ndarray]:
    obj = np.array(town.static.obj)
    rows = np.array(town.static.rows)
    ids = [i for i, c in enumerate(town.objects) if c == cls]
    return [rows[obj == i] for i in ids if (obj == i).any()]


def test_each_style_has_what_it_claims():
    styles = ("grid", "suburban", "industrial", "park", "parking", "terrace")
    towns = {s: Town(5, TownParams(**SMALL, style=s)) for s in styles}
    streets_km = {s: sum(st.length for st in t.streets) / 1000 for s, t in towns.items()}
    for style, town in towns.items():  # each makes a street scene a sensor sees
        pose = plan_sessions(town, get_sensor("vlp16"), 1, 4, 5.0, 5)[0].poses[2]
        pts = scan(town.session_world(0), pose, "vlp16", seed=1, town=town)
        assert len(pts) > 10_000 and (pts[:, 2] > -1.0).mean() > 0.05, style

    def footprints(style: str) -> np.ndarray:  # of each building's largest box, m2
        return np.array(
            [4 * (b[:, 4] * b[:, 5]).max() for b in _objects(towns[style], "buildings")]
        )

    def trees_per_km(style: str) -> float:
        return len(_objects(towns[style], "trees")) / streets_km[style]

    # Suburban: detached houses (small, low) with gardens (hedges, trees).
    houses = [b for b in _objects(towns["suburban"], "buildings") if b[0, 6] > 2]
    assert len(houses) > 20
    assert np.median(footprints("suburban")) < 0.5 * np.median(footprints("grid"))
    heights = np.array([2 * b[0, 6] - 0.3 for b in houses])  # main box, sunk 0.3 m
    assert np.all(heights <= 9.0 + 1e-9) and np.median(heights) >= 5.0
    assert len(_objects(towns["suburban"], "hedges")) > len(_objects(towns["grid"], "hedges"))
    # Industrial: halls of more than 600 m2, and shipping containers (6.06 x 2.44 m).
    assert (footprints("industrial") > 600).sum() >= 5
    containers = [
        b
        for b in _objects(towns["industrial"], "buildings")
        if np.allclose(2 * b[:, 4:6], [6.06, 2.44])
    ]
    assert len(containers) >= 3
    # Park: a tree-lined road, about twice the trees of the grid town, few buildings.
    assert trees_per_km("park") > 2 * trees_per_km("grid")
    assert len(footprints("park")) < 0.5 * len(footprints("grid"))
    # Parking: lots of spots square to their street.
    town = towns["parking"]
    square = 0
    for c, yaw, _ in town._parking:
        near = min(
            town.streets,
            key=lambda s: abs((c - s.a) @ s.left) + 1e3 * (not 0 <= (c - s.a) @ s.dir <= s.length),
        )
        square += abs(np.cos(yaw - near.yaw)) < 0.05
    assert square > 100
    # Terrace: narrow houses in a row, 0.3 m apart, each within 0.8 m of its neighbours'
    # height, and more cars parked along the kerbs than in the grid town.
    rows = [b[0] for b in _objects(towns["terrace"], "buildings") if b[0, 6] > 2]
    widths = np.array([2 * r[4] for r in rows])
    assert len(rows) > 60 and np.median(widths) < 7.0
    neighbours = 0
    for i, a in enumerate(rows):
        for b in rows[i + 1 :]:
            gap = np.hypot(a[1] - b[1], a[2] - b[2]) - (a[4] + b[4])
            if abs(gap - 0.3) < 0.05 and abs(np.cos(a[7] - b[7])) > 0.999:
                neighbours += 1
                assert abs(a[6] - b[6]) <= 0.4 + 1e-9  # half heights: within 0.8 m
    assert neighbours > 0.5 * len(rows)
    assert len(towns["terrace"]._parking) > 1.5 * len(towns["grid"]._parking)


def test_varied_terrain_crowns_the_roads_and_the_car_rides_on_them():
    town = Town(5, TownParams(**SMALL, terrain="varied"))
    s = town.streets[0]
    mid = s.a + s.dir * s.length / 2
    rise = town.surface_z(*mid) - town.ground_z(*mid)
    assert rise == pytest.approx(0.02 * s.half_width, abs=1e-9)
    edge = mid + s.left * (s.half_width - 0.2)
    assert town.surface_z(*edge) == pytest.approx(town.ground_z(*edge))
    # The crown is there for the ray caster too: a ray straight down at the centre line.
    world = town.session_world(0)
    T = np.eye(4)
    T[:3, 3] = [*mid, town.ground_z(*mid) + 3.0]
    r, ids, _ = world.caster.cast_scans(
        T[None], np.array([[0, 0, -1.0]], np.float32), 10.0, np.array([1], np.uint64), 1
    )
    assert ids[0, 0] >= 0 and r[0, 0] == pytest.approx(3.0 - rise, abs=1e-4)
    plan = plan_sessions(town, get_sensor("hdl32"), 1, 30, 3.0, 5)[0]
    p = plan.poses[:, :3, 3]
    above = p[:, 2] - town.surface_z(p[:, 0], p[:, 1])
    assert np.all(np.abs(above - 1.8) < 0.05)
    assert np.ptp(town.surface_z(p[:, 0], p[:, 1]) - town.ground_z(p[:, 0], p[:, 1])) > 0.03


def test_robot_randomization_stays_in_bounds_and_is_in_the_poses(tmp_path):
    robot = RobotParams(height_m=(0.5, 2.5), tilt_deg=5.0, offset_m=4.0, sensor="random")
    params = TownParams(**SMALL, max_slope=0.0)  # a flat ground plane z = 0
    meta = simulate(
        tmp_path,
        sessions=4,
        frames=3,
        step_m=4.0,
        sensor="hdl32",
        seed=8,
        params=params,
        robot=robot,
        threads=1,
    )
    town = Town(8, params)
    plans = plan_sessions(town, get_sensor("hdl32"), 4, 3, 4.0, 8, robot)
    offsets0 = meta["sessions"][0]["offset_right_m"]
    for k, entry in enumerate(meta["sessions"][1:], start=1):
        h, roll, pitch = entry["mount_height_m"], entry["mount_roll_deg"], entry["mount_pitch_deg"]
        assert 0.5 <= h <= 2.5 and abs(roll) <= 5 and abs(pitch) <= 5
        sensor = get_sensor(entry["sensor"]["name"])
        assert 16 <= sensor.beams <= 128
        assert entry["sensor"]["elevations_deg"] == [round(e, 4) for e in sensor.elevations_deg]
        # Offset: within 4 m of session 00's driving line, inside the road.
        off = entry["offset_right_m"]
        line = -off if k % 2 else off
        assert abs(line - offsets0) <= 4.0 + 1e-6 and abs(off) <= 2.5
        poses = read_kitti_poses(tmp_path / entry["name"] / "poses.txt")
        np.testing.assert_allclose(poses, plans[k].poses, atol=1e-6)
        for i in (0, 2):
            T = poses[i]
            # The sensor rides h above the ground (the car sways by < 1 degree).
            assert T[2, 3] == pytest.approx(h, abs=0.01)
            pts = np.fromfile(tmp_path / entry["name"] / "velodyne" / f"{i:06d}.bin", np.float32)
            pts = pts.reshape(-1, 4)[:, :3].astype(np.float64)
            # Every point comes from one of this sensor's beams.
            el = np.degrees(np.arcsin(pts[:, 2] / np.linalg.norm(pts, axis=1)))
            gap = np.abs(el[:, None] - np.array(sensor.elevations_deg)[None]).min(axis=1)
            assert np.percentile(gap, 99.9) < 0.01
            # Re-projected with the written pose, the ground is at z = 0 (kerbs and
            # crowns aside): many points within 6 cm of it. Without the mount's tilt
            # they would not be.
            world = pts @ T[:3, :3].T + T[:3, 3]
            on_ground = np.abs(world[:, 2]) < 0.06
            assert on_ground.mean() > 0.3, (k, i, on_ground.mean())
            if max(abs(roll), abs(pitch)) > 2:
                from scipy.spatial.transform import Rotation

                untilt = Rotation.from_euler("YX", [pitch, roll], degrees=True).as_matrix()
                R = T[:3, :3] @ untilt.T
                wrong = pts @ R.T + T[:3, 3]
                assert (np.abs(wrong[:, 2]) < 0.06).mean() < 0.6 * on_ground.mean()
    # Session 00 keeps the sensor asked for.
    assert "sensor" not in meta["sessions"][0] or meta["sessions"][0]["sensor"]["name"] == "hdl32"


def test_made_up_sensors():
    for layout in ("uniform", "hdl64like"):
        for beams in (16, 40, 128):
            s = get_sensor(f"{layout}-{beams}")
            el = np.array(s.elevations_deg)
            assert s.beams == beams and np.all(np.diff(el) < 0)
            if layout == "uniform":
                assert el[0] == 15.0 and el[-1] == -25.0 and np.ptp(np.diff(el)) < 1e-3
            else:  # dense above -8.5 degrees, sparser below, as the HDL-64E
                up, low = np.diff(el[el > -8.5]), np.diff(el[el < -8.5])
                assert np.abs(up).mean() < np.abs(low).mean()
    for bad in ("uniform-8", "uniform-200", "hdl64like-x", "fisheye-32"):
        with pytest.raises(DiscoError):
            get_sensor(bad)
    with pytest.raises(DiscoError, match="robot-height"):
        RobotParams(height_m=(0.1, 5.0)).check()
