"""The synthetic LiDAR world: ray casting against a NumPy reference, geometry, noise,
see-through crowns, determinism, sessions with reverse revisits, and the two commands."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.io.poses import gt_pairs, gt_pairs_within, read_kitti_poses, relative_yaw_deg
from disco_cli.simulator import cast, get_sensor, plan_sessions, scan, simulate
from disco_cli.simulator.world import (
    BOX,
    CYLINDER,
    ELLIPSOID,
    Town,
    TownParams,
    primitives_world,
    wall_world,
)

SMALL = TownParams(blocks_x=2, blocks_y=2, outskirts_m=30.0)


def rot(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def pose(
    x: float, y: float, z: float, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0
) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot(yaw, pitch, roll)
    T[:3, 3] = [x, y, z]
    return T


# -- a plain NumPy ray caster, written independently of the C++ one -----------
def ref_hit(row: np.ndarray, o: np.ndarray, d: np.ndarray) -> float:
    kind, cx, cy, cz, hx, hy, hz, yaw, _ = row
    rel = o - [cx, cy, cz]
    ts = []
    if kind == BOX:
        R = rot(np.degrees(yaw))
        lo, ld = R.T @ rel, R.T @ d
        h = np.array([hx, hy, hz])
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (-h - lo) / ld, (h - lo) / ld
        t0 = np.max(np.minimum(ta, tb))
        t1 = np.min(np.maximum(ta, tb))
        if t0 <= t1:
            ts += [t0, t1]
    elif kind == CYLINDER:
        a = d[0] ** 2 + d[1] ** 2
        b = rel[0] * d[0] + rel[1] * d[1]
        c = rel[0] ** 2 + rel[1] ** 2 - hx**2
        if a > 1e-12 and b * b - a * c >= 0:  # the side (a vertical ray never hits it)
            for t in ((-b - np.sqrt(b * b - a * c)) / a, (-b + np.sqrt(b * b - a * c)) / a):
                if abs(rel[2] + t * d[2]) <= hz:
                    ts.append(t)
        for zc in (hz, -hz) if abs(d[2]) > 1e-12 else ():  # top and bottom
            t = (zc - rel[2]) / d[2]
            if np.hypot(rel[0] + t * d[0], rel[1] + t * d[1]) <= hx:
                ts.append(t)
    else:
        s = np.array([1 / hx, 1 / hx, 1 / hz])
        so, sd = rel * s, d * s
        a, b, c = sd @ sd, so @ sd, so @ so - 1
        if b * b - a * c >= 0:
            ts += [(-b - np.sqrt(b * b - a * c)) / a, (-b + np.sqrt(b * b - a * c)) / a]
    ts = [t for t in ts if t > 1e-6]
    return min(ts) if ts else np.inf


def random_table(rng: np.random.Generator, n: int) -> np.ndarray:
    rows = []
    for _ in range(n):
        kind = rng.integers(3)
        c = [*rng.uniform(-40, 40, 2), rng.uniform(0, 6)]
        if kind == BOX:
            rows.append([BOX, *c, *rng.uniform(0.2, 6, 3), rng.uniform(-np.pi, np.pi), 1])
        elif kind == CYLINDER:
            r = rng.uniform(0.1, 1.5)
            rows.append([CYLINDER, *c, r, r, rng.uniform(0.5, 5), 0, 1])
        else:
            r = rng.uniform(0.5, 4)
            rows.append([ELLIPSOID, *c, r, r, rng.uniform(0.5, 4), 0, 1])
    return np.array(rows, float)


def test_ray_casting_matches_a_numpy_reference():
    rng = np.random.default_rng(0)
    table = random_table(rng, 60)
    ground = (0.01, -0.02, -0.5)
    world = primitives_world(table, ground, cell_size=3.0)
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origin = np.array([1.0, -2.0, 2.0])
    T = pose(*origin)
    ranges, ids, _ = world.caster.cast_scans(
        T[None], dirs.astype(np.float32), 80.0, np.array([1], np.uint64), 1
    )
    d32 = dirs.astype(np.float32).astype(np.float64)
    d32 /= np.linalg.norm(d32, axis=1, keepdims=True)
    n_objects = 0
    for r in range(len(dirs)):
        d = d32[r]
        t = np.array([ref_hit(row, origin, d) for row in table])
        a, b, c = ground
        denom = d[2] - a * d[0] - b * d[1]
        tg = (a * origin[0] + b * origin[1] + c - origin[2]) / denom if denom < 0 else np.inf
        best = min(t.min(), tg)
        if best >= 80.0:
            assert ids[0, r] == -2 and ranges[0, r] == 0
        elif tg <= t.min():
            assert ids[0, r] == -1
            assert ranges[0, r] == pytest.approx(tg, abs=1e-4)
        else:
            n_objects += 1
            assert ids[0, r] == int(np.argmin(t)), f"ray {r}"
            assert ranges[0, r] == pytest.approx(t.min(), abs=1e-4)
    assert n_objects > 20  # the test exercised the grid, not only the ground


@pytest.mark.parametrize("origin", [(1.0, -2.0, 2.0), (-120.0, 75.0, 3.0), (40.0, 40.0, 30.0)])
def test_axis_aligned_vertical_and_outside_rays_match_the_reference(origin):
    # Rays along the grid axes, straight up and down, at exactly 45 degrees, and from
    # outside the grid: the DDA's special cases.
    rng = np.random.default_rng(1)
    table = random_table(rng, 40)
    world = primitives_world(table, (0.0, 0.0, 0.0), cell_size=4.0)
    dirs = [
        (1, 0, 0),
        (-1, 0, 0),
        (0, 1, 0),
        (0, -1, 0),
        (0, 0, 1),
        (0, 0, -1),
        (1, 1, 0),
        (-1, 1, -0.1),
        (1, -1, 0.05),
        (1e-9, 1, 0),
        (0.3, 0.2, -1),
    ]
    towards = -np.array(origin) / np.linalg.norm(origin)  # at the town's centre
    dirs = np.array(dirs + [tuple(towards)] * 1, float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = np.array(origin)
    ranges, ids, _ = world.caster.cast_scans(
        pose(*o)[None], dirs.astype(np.float32), 500.0, np.array([1], np.uint64), 1
    )
    for r, d in enumerate(dirs.astype(np.float32).astype(np.float64)):
        d /= np.linalg.norm(d)
        t = np.array([ref_hit(row, o, d) for row in table])
        tg = -o[2] / d[2] if d[2] < 0 else np.inf
        if min(t.min(), tg) >= 500.0:
            assert ids[0, r] == -2
        elif tg <= t.min():
            assert ids[0, r] == -1 and ranges[0, r] == pytest.approx(tg, abs=1e-4)
        else:
            assert ids[0, r] == int(np.argmin(t)) and ranges[0, r] == pytest.approx(
                t.min(), abs=1e-4
            )


def test_caster_rejects_bad_tables_and_poses():
    from disco_cli import _core

    with pytest.raises(ValueError, match="N x 9"):
        _core.RaycastWorld(np.zeros((3, 8)), 0, 0, 0, 4.0)
    with pytest.raises(ValueError, match="kind"):
        _core.RaycastWorld(np.array([[7, 0, 0, 0, 1, 1, 1, 0, 1.0]]), 0, 0, 0, 4.0)
    world = primitives_world(np.zeros((0, 9)))
    with pytest.raises(ValueError, match="4 x 4"):
        world.caster.cast_scans(
            np.eye(3)[None], np.ones((2, 3), np.float32), 10.0, np.array([1], np.uint64), 1
        )
    with pytest.raises(ValueError, match="one seed per pose"):
        world.caster.cast_scans(
            np.eye(4)[None], np.ones((2, 3), np.float32), 10.0, np.array([1, 2], np.uint64), 1
        )
    # An empty world still has its ground.
    r, ids, _ = world.caster.cast_scans(
        pose(0, 0, 2)[None], np.array([[1, 0, -1]], np.float32), 10.0, np.array([1], np.uint64), 1
    )
    assert ids[0, 0] == -1 and r[0, 0] == pytest.approx(2 * np.sqrt(2), abs=1e-5)


def test_wall_at_known_distance_within_noise():
    sensor = get_sensor("hdl32")
    world = wall_world(distance=12.0, height=8.0, length=200.0)
    h = 1.8
    pts = scan(world, pose(0, 0, h), sensor, seed=3)
    assert pts.dtype == np.float32 and pts.shape[1] == 4
    # Every point lies on the ground plane (z = -h) or on the wall's face (x = 12),
    # within the noise: sigma * (1 + r/R) < 0.03 m here, so a 5-sigma bound.
    on_ground = np.abs(pts[:, 2] + h) < 0.15
    wall = pts[~on_ground]
    assert len(wall) > 1000 and on_ground.sum() > 1000
    assert np.all(np.abs(wall[:, 0] - 12.0) < 0.15)
    assert np.std(wall[:, 0] - 12.0) < 0.04
    assert np.std(pts[on_ground, 2] + h) < 0.02
    # Nothing above the wall's top (z = 8 - h) and nothing behind it.
    assert wall[:, 2].max() < 8.0 - h + 0.1
    assert pts[:, 0].max() < 12.0 + 0.15
    # Intensities are plausible: within [0, 1], and not all equal.
    assert 0 <= pts[:, 3].min() and pts[:, 3].max() <= 1 and pts[:, 3].std() > 0.01


def test_a_static_object_sits_still_from_two_poses():
    # A box with its -x face at x = 20 (world), seen from two poses turned and tilted.
    table = np.array([[BOX, 21.0, 3.0, 3.0, 1.0, 2.0, 3.0, 0.0, 1.0]])
    world = primitives_world(table)
    faces = []
    for T in (pose(0, 0, 1.8, yaw=10), pose(6, 5, 1.9, yaw=-30, pitch=2, roll=-1.5)):
        pts = scan(world, T, "hdl64", seed=5).astype(np.float64)
        xyz = pts[:, :3] @ T[:3, :3].T + T[:3, 3]
        face = xyz[(xyz[:, 2] > 0.3) & (np.abs(xyz[:, 1] - 3.0) < 1.9) & (xyz[:, 0] < 20.5)]
        assert len(face) > 100
        faces.append(face)
        assert np.all(np.abs(face[:, 0] - 20.0) < 0.15)
    assert np.mean(faces[0][:, 0]) == pytest.approx(np.mean(faces[1][:, 0]), abs=0.01)


def test_tree_crowns_are_partly_see_through():
    # A crown (hit probability 0.4) in front of a wall: about 40 % of the rays that
    # cross it stop on it; the others reach the wall.
    p = 0.4
    table = np.array(
        [
            [ELLIPSOID, 10.0, 0.0, 2.0, 2.0, 2.0, 2.0, 0.0, p],
            [BOX, 20.5, 0.0, 5.0, 0.5, 30.0, 5.0, 0.0, 1.0],
        ]
    )
    world = primitives_world(table)
    sensor = get_sensor("hdl64")
    ranges, ids, _ = cast(world, pose(0, 0, 2.0), sensor, np.array([7], np.uint64))
    d = sensor.directions().astype(np.float64)
    # Rays whose line crosses the crown (unit-sphere test in the scaled frame).
    rel = np.array([0.0, 0.0, 0.0]) - [10.0, 0.0, 0.0]
    b = d @ rel / 4.0
    c = rel @ rel / 4.0 - 1.0
    crosses = (b * b - (d * d).sum(1) / 4.0 * c > 0.05) & (d[:, 0] > 0)
    n = int(crosses.sum())
    assert n > 500
    frac = float((ids[0][crosses] == 0).mean())
    assert abs(frac - p) < 4 * np.sqrt(p * (1 - p) / n)
    assert np.all(np.isin(ids[0][crosses], [0, 1, -1]))  # the crown, or the wall or ground behind
    # Another scan seed decides differently, ray by ray.
    _, ids2, _ = cast(world, pose(0, 0, 2.0), sensor, np.array([8], np.uint64))
    assert (ids[0][crosses] != ids2[0][crosses]).mean() > 0.2


def test_sensor_patterns():
    for name, beams, lo, hi in (
        ("hdl32", 32, -30.67, 10.67),
        ("hdl64", 64, -24.9, 2.0),
        ("vlp16", 16, -15.0, 15.0),
        ("os1-64", 64, -16.6, 16.6),
    ):
        s = get_sensor(name)
        el = np.degrees(np.arcsin(s.directions()[:, 2].astype(np.float64)))
        assert s.beams == beams
        assert el.min() == pytest.approx(lo, abs=1e-3) and el.max() == pytest.approx(hi, abs=1e-3)
        assert 0.1 <= s.azimuth_step_deg <= 0.4 and 100 <= s.max_range <= 120
        np.testing.assert_allclose(np.linalg.norm(s.directions(), axis=1), 1.0, atol=1e-6)


def test_town_scan_looks_like_a_street():
    town = Town(11, SMALL)
    sensor = get_sensor("hdl32")
    plan = plan_sessions(town, sensor, 1, 60, 2.0, 11)[0]
    pts = scan(town.session_world(0), plan.poses[10], sensor, seed=1, town=town)
    assert 20_000 < len(pts) < 40_000  # the ~30k points of a 32-beam scan
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert r.max() <= sensor.max_range + 0.5 and r.min() >= sensor.min_range - 0.1
    above = pts[pts[:, 2] > -1.0]  # walls, trees, poles, cars: not only the ground
    assert len(above) > 0.15 * len(pts)
    assert np.isfinite(pts).all() and 0 <= pts[:, 3].min() and pts[:, 3].max() <= 1


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path):
    kw = dict(sessions=2, frames=3, step_m=5.0, sensor="vlp16", params=SMALL)
    simulate(tmp_path / "a", seed=4, threads=1, **kw)
    simulate(tmp_path / "b", seed=4, threads=2, **kw)
    simulate(tmp_path / "c", seed=5, threads=1, **kw)
    root = tmp_path / "a"
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert len(files) == 2 * (3 + 2) + 1
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert (tmp_path / "a/00/velodyne/000000.bin").read_bytes() != (
        tmp_path / "c/00/velodyne/000000.bin"
    ).read_bytes()
    meta = json.loads((tmp_path / "a/world.json").read_text())
    assert meta["seed"] == 4 and meta["sensor"]["name"] == "vlp16"
    assert meta["town"]["params"]["blocks_x"] == 2
    poses = read_kitti_poses(tmp_path / "a/01/poses.txt")
    assert poses.shape == (3, 4, 4)


def test_sessions_revisit_in_the_opposite_direction():
    town = Town(2)
    plans = plan_sessions(town, get_sensor("hdl32"), 2, 300, 2.0, 2)
    a, b = plans[0].poses, plans[1].poses
    pairs = gt_pairs(b, a, 3.0)
    yaw = relative_yaw_deg(a[pairs[:, 1]], b[pairs[:, 0]])
    assert np.sum(np.abs(yaw) > 150) >= 5
    # Scan positions do not coincide across sessions.
    d = np.linalg.norm(b[pairs[:, 0], :3, 3] - a[pairs[:, 1], :3, 3], axis=1)
    assert d.min() > 0.2
    # Session 00 closes its loop: late frames come back to early ones.
    loops = gt_pairs_within(a, 3.0, exclude_frames=50)
    assert len(loops) > 0 and loops[:, 1].min() < 10
    # Poses are rigid, and the sensor rides at mount height over the ground.
    R = a[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(a), 1, 1)), atol=1e-9
    )
    z_ground = town.ground_z(a[:, 0, 3], a[:, 1, 3])
    assert np.all(np.abs(a[:, 2, 3] - z_ground - 1.8) < 0.05)


def test_changeable_things_differ_between_sessions():
    town = Town(3, SMALL)
    t0, t1 = town.session_world(0).table, town.session_world(1).table
    n_static = len(town.static.rows)
    # The static town stands still, but for how dense the foliage is.
    np.testing.assert_array_equal(t0[:n_static, :8], t1[:n_static, :8])
    base = np.array(town.static.rows)[:, 8]
    leafy = (t0[:n_static, 0] == ELLIPSOID) & (base < 1.0)
    assert leafy.sum() > 20
    np.testing.assert_array_equal(t0[:n_static][~leafy, 8], base[~leafy])
    # One factor per session (unless clipped), in the configured range.
    for t in (t0, t1):
        ratio = t[:n_static][leafy, 8] / base[leafy]
        inside = (t[:n_static][leafy, 8] > 0.05) & (t[:n_static][leafy, 8] < 0.95)
        assert np.ptp(ratio[inside]) < 1e-9
        assert SMALL.foliage[0] <= ratio[inside][0] <= SMALL.foliage[1]
    # Parked cars, bins and some trees differ.
    assert len(t0) != len(t1) or not np.array_equal(t0[n_static:], t1[n_static:])


def test_cli_simulate_and_gt_loops(tmp_path):
    runner = CliRunner()
    out = tmp_path / "sim"
    res = runner.invoke(
        app,
        [
            "simulate",
            str(out),
            "--sessions",
            "2",
            "--frames",
            "2",
            "--step-m",
            "4",
            "--sensor",
            "vlp16",
            "--seed",
            "1",
        ],
    )
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "00" / "velodyne").iterdir()) == [
        "000000.bin",
        "000001.bin",
    ]
    # A second run refuses to overwrite without --force.
    res = runner.invoke(app, ["simulate", str(out), "--frames", "2"])
    assert res.exit_code == 1 and "--force" in res.output
    res = runner.invoke(app, ["simulate", str(out), "--frames", "2", "--length-m", "9"])
    assert res.exit_code == 1 and "not both" in res.output


def test_gt_loops_lists_exactly_the_pairs_within_the_radius(samples):
    runner = CliRunner()
    res = runner.invoke(
        app,
        ["gt-loops", str(samples / "00"), str(samples / "01"), "--radius", "3", "--format", "tsv"],
    )
    assert res.exit_code == 0, res.output
    lines = res.stdout.strip().splitlines()
    assert lines[0].split("\t") == [
        "query_seq",
        "query",
        "match_seq",
        "match",
        "distance_m",
        "yaw_deg",
    ]
    rows = [line.split("\t") for line in lines[1:]]
    a = read_kitti_poses(samples / "00" / "poses.txt")
    b = read_kitti_poses(samples / "01" / "poses.txt")
    d = np.linalg.norm(b[:, None, :3, 3] - a[None, :, :3, 3], axis=-1)
    assert {(int(r[1]), int(r[3])) for r in rows} == {tuple(p) for p in np.argwhere(d <= 3.0)}
    # The sample's second session drives back the other way.
    assert any(abs(float(r[5])) > 150 for r in rows)
    res = runner.invoke(
        app, ["gt-loops", str(samples / "00"), "--exclude-frames", "5", "--format", "jsonl"]
    )
    rows = [json.loads(line) for line in res.stdout.strip().splitlines()]
    assert rows and all(r["query"] - r["match"] >= 5 and r["distance_m"] <= 3 for r in rows)


def test_gt_loops_bad_input_is_one_line(tmp_path):
    runner = CliRunner()
    (tmp_path / "seq").mkdir()
    res = runner.invoke(app, ["gt-loops", str(tmp_path / "seq")])
    assert res.exit_code == 1 and "no poses.txt" in res.output
    (tmp_path / "seq" / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    res = runner.invoke(app, ["gt-loops", str(tmp_path / "seq")])
    assert res.exit_code == 1 and "line 1" in res.output and "Traceback" not in res.output


def test_sample_is_small_and_complete(samples):
    total = sum(p.stat().st_size for p in samples.rglob("*") if p.is_file())
    assert total <= 15_000_000
    meta = json.loads((samples / "world.json").read_text())
    for s in ("00", "01"):
        n = len(list((samples / s / "velodyne").glob("*.bin")))
        assert n == meta["sessions"][int(s)]["frames"]
        assert len(read_kitti_poses(samples / s / "poses.txt")) == n
    a = read_kitti_poses(samples / "00" / "poses.txt")
    assert len(gt_pairs_within(a, 3.0, exclude_frames=5)) > 0


def _numbers(text: str) -> np.ndarray:
    return np.array([float(t) for t in re.findall(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?", text)])


def test_sample_regenerates(samples, tmp_path):
    # The command recorded in the sample's README and world.json rewrites it. The scenes
    # must be the same; the last bit of a float may not be: NumPy's and libm's sine and
    # cosine round differently on CPUs with and without AVX-512, so points may move by
    # far less than a micrometre. Stated tolerance: every coordinate within 1e-4 m
    # (intensity within 1e-4), and at most 1 value in 10,000 not bit-identical.
    meta = json.loads((samples / "world.json").read_text())
    readme = (samples / "README.md").read_text()
    args = meta["command"].split()[3:]  # after "disco simulate OUT"
    assert meta["command"].replace("OUT", "data/samples") + " --force" in readme
    res = CliRunner().invoke(app, ["simulate", str(tmp_path / "again"), *args])
    assert res.exit_code == 0, res.output
    committed = sorted(
        p.relative_to(samples) for p in samples.rglob("*") if p.is_file() and p.name != "README.md"
    )
    again = sorted(
        p.relative_to(tmp_path / "again") for p in (tmp_path / "again").rglob("*") if p.is_file()
    )
    assert committed == again
    differing = total = 0
    for rel in committed:
        a_bytes, b_bytes = (samples / rel).read_bytes(), (tmp_path / "again" / rel).read_bytes()
        if rel.suffix == ".bin":
            a = np.frombuffer(a_bytes, np.float32).reshape(-1, 4)
            b = np.frombuffer(b_bytes, np.float32).reshape(-1, 4)
            assert a.shape == b.shape, rel
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-4, err_msg=str(rel))
            differing += int(np.count_nonzero(a != b))
            total += a.size
        elif a_bytes != b_bytes:
            # Text (poses, times, world.json): the same numbers, to 1e-6 relative.
            a_num, b_num = _numbers(a_bytes.decode()), _numbers(b_bytes.decode())
            assert a_num.shape == b_num.shape, rel
            np.testing.assert_allclose(b_num, a_num, rtol=1e-6, atol=1e-9, err_msg=str(rel))
    assert total > 0
    assert differing <= total // 10_000, (differing, total)


def test_the_car_follows_the_slope():
    # On a 5 % slope the car pitches and rolls with the ground, so in the sensor frame
    # the ground is level within the car's own sway (< 1 deg), 1.8 m below.
    town = Town(5, TownParams(blocks_x=2, blocks_y=2, outskirts_m=30.0, max_slope=0.05))
    a, b, _ = town.ground
    assert np.hypot(a, b) > 0.015
    sensor = get_sensor("hdl32")
    plan = plan_sessions(town, sensor, 1, 40, 3.0, 5)[0]
    world = town.session_world(0)
    d = sensor.directions().astype(np.float64)
    for i in (5, 20, 35):
        ranges, ids, _ = cast(world, plan.poses[i], sensor, np.array([i], np.uint64))
        g = (ids[0] == -1) & (ranges[0] < 30)
        p = d[g] * ranges[0][g, None]
        A = np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))])
        (ga, gb, gc), *_ = np.linalg.lstsq(A, p[:, 2], rcond=None)
        assert np.degrees(np.arctan(np.hypot(ga, gb))) < 1.0
        assert gc == pytest.approx(-1.8, abs=0.05)
        # The world slope seen from a car that did not pitch would be 1.5-3 deg.
        world_tilt = np.degrees(np.arctan(np.hypot(a, b)))
        assert world_tilt > 0.8


def test_cars_drive_on_their_right_and_keep_clear_of_the_sensor():
    town = Town(3, SMALL)
    s = town.streets[0]
    lo = float(town.node_clear[town.links[0][0]])
    # One car heading along the street at 10 m/s, 1.8 m right of the centre line.
    car = np.array([[0, 1.0, 5.0, 10.0, 1.8, 4.5, 1.8, 1.5, 0.5, 0, lo, 30.0]])
    rows0, refl, _ = town.mover_rows(car, 0.0, None, 8.0)
    rows1, _, _ = town.mover_rows(car, 1.0, None, 8.0)
    assert len(rows0) == 2 and len(refl) == 2  # body and cabin
    c0, c1 = rows0[0, 1:3], rows1[0, 1:3]
    np.testing.assert_allclose(c1 - c0, 10.0 * s.dir, atol=1e-9)
    assert (c0 - s.a) @ s.dir == pytest.approx(lo + 5.0)
    assert (c0 - s.a) @ s.left == pytest.approx(-1.8)  # right of its heading
    # The other way round it drives on the other side, and wraps within its span.
    back = car.copy()
    back[0, 1] = -1.0
    rows_b, _, _ = town.mover_rows(back, 1.0, None, 8.0)
    pos = rows_b[0, 1:3] - s.a
    assert pos @ s.left == pytest.approx(1.8)
    assert pos @ s.dir == pytest.approx(lo + (5.0 - 10.0) % 30.0)
    # Nothing within the clear radius of the sensor.
    none, _, _ = town.mover_rows(car, 0.0, c0 + [3.0, 0.0], 8.0)
    assert len(none) == 0
    # A session world has traffic and walkers, placed per time.
    world = town.session_world(0)
    assert world.movers is not None and (world.movers[:, 9] == 0).any()
    assert (world.movers[:, 9] == 1).any()
    assert len(world.at(2.0).table) > len(world.table)


def test_motion_distortion_measures_each_ray_from_where_the_sensor_fired():
    from disco_cli.simulator import sweep_poses

    sensor = get_sensor("hdl32")
    world = wall_world(distance=12.0, height=8.0, length=200.0)
    f_ray = sensor.fractions().astype(np.float64)
    d = sensor.directions().astype(np.float64)
    # Driving at the wall, 1 m per sweep: the sweep starts half a metre back.
    start, end = pose(-0.5, 0, 1.8), pose(0.5, 0, 1.8)
    r, ids, _ = cast(world, start, sensor, np.array([1], np.uint64), poses_end=end)
    wall = ids[0] == 0
    x = d[wall, 0] * r[0][wall]
    # In the sensor frame of its own firing time: 12 - (sensor x then).
    np.testing.assert_allclose(x, 12.0 - (-0.5 + f_ray[wall]), atol=1e-4)
    # The forward ray fires half-way (at the scan's pose), the rear one first.
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    assert f_ray[np.argmin(np.abs(az))] == pytest.approx(0.5)
    assert f_ray[np.argmin(np.abs(az - 90))] == pytest.approx(0.25, abs=0.002)
    # Turning 4 degrees during the sweep: each point, put back with the rotation of its
    # own firing time, lies on the wall.
    r, ids, _ = cast(
        world,
        pose(0, 0, 1.8, yaw=-2),
        sensor,
        np.array([1], np.uint64),
        poses_end=pose(0, 0, 1.8, yaw=2),
    )
    wall = ids[0] == 0
    p = d[wall] * r[0][wall, None]
    yaw = np.radians(-2 + 4 * f_ray[wall])
    np.testing.assert_allclose(np.cos(yaw) * p[:, 0] - np.sin(yaw) * p[:, 1], 12.0, atol=2e-3)
    # Sweep bounds of steady driving: half a step either side, extrapolated at the ends.
    steady = np.stack([pose(2.0 * i, 0, 1.8, yaw=3 * i) for i in range(4)])
    starts, ends = sweep_poses(steady)
    for i in range(4):
        np.testing.assert_allclose(starts[i], pose(2.0 * i - 1, 0, 1.8, yaw=3 * i - 1.5), atol=1e-9)
        np.testing.assert_allclose(ends[i], pose(2.0 * i + 1, 0, 1.8, yaw=3 * i + 1.5), atol=1e-9)


def test_town_parameters_from_toml_or_world_json(tmp_path):
    from disco_cli.errors import DiscoError

    (tmp_path / "town.toml").write_text(
        "[town]\nblocks_x = 2\nblocks_y = 3\nroad_width_m = [9, 10]\ntraffic_per_km = 0\n"
    )
    params = TownParams.load(tmp_path / "town.toml")
    assert (params.blocks_x, params.blocks_y, params.road_width_m) == (2, 3, (9.0, 10.0))
    assert params.traffic_per_km == 0.0 and params.max_slope == TownParams().max_slope
    town = Town(1, params)
    assert len(town.nodes) == 3 * 4
    widths = [2 * s.half_width for s in town.streets]
    assert 9.0 <= min(widths) and max(widths) <= 10.0
    assert not (town.session_world(0).movers[:, 9] == 0).any()  # no traffic
    # A world.json carries the parameters it was made with; the CLI takes either file.
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "simulate",
            str(tmp_path / "a"),
            "--frames",
            "2",
            "--sessions",
            "1",
            "--sensor",
            "vlp16",
            "--town",
            str(tmp_path / "town.toml"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert TownParams.load(tmp_path / "a" / "world.json") == params
    meta = json.loads((tmp_path / "a" / "world.json").read_text())
    assert "--town OUT/world.json" in meta["command"]
    res = runner.invoke(
        app,
        [
            "simulate",
            str(tmp_path / "b"),
            "--frames",
            "2",
            "--sessions",
            "1",
            "--sensor",
            "vlp16",
            "--town",
            str(tmp_path / "a" / "world.json"),
        ],
    )
    assert res.exit_code == 0, res.output
    for f in ("00/poses.txt", "00/velodyne/000001.bin", "world.json"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    # Unknown keys, wrong types and impossible values: one clear error naming the file.
    for text, what in (
        ("foo = 1\n", "unknown town parameters: foo"),
        ("blocks_x = 'a'\n", "blocks_x"),
        ("blocks_x = 1.5\n", "blocks_x"),
        ("block_min_m = 90\nblock_max_m = 60\n", "block_min_m"),
        ("road_width_m = [10]\n", "road_width_m"),
        ("blocks_x = [\n", "TOML"),
    ):
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(DiscoError, match=what) as info:
            TownParams.load(tmp_path / "bad.toml")
        assert "bad.toml" in str(info.value)
    res = runner.invoke(
        app,
        ["simulate", str(tmp_path / "c"), "--frames", "2", "--town", str(tmp_path / "bad.toml")],
    )
    assert res.exit_code == 1 and "bad.toml" in res.output and "Traceback" not in res.output


def test_documented_town_defaults_are_the_defaults():
    from pathlib import Path

    import tomllib

    text = (Path(__file__).parent.parent / "docs" / "simulator.md").read_text()
    block = text[text.index("```toml") + len("```toml") :]
    block = block[: block.index("```")]
    assert TownParams.from_dict(tomllib.loads(block)["town"]) == TownParams()
