"""Augmentation (beam decimation, dropout, wedge occlusion, tilt, z shift) against
independent references, augmented copies in the training data, and a short seeded run on
a world that changes between sessions that must beat the untrained network on another
changed world."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import short_training

from disco_cli.training.augment import (
    AugmentConfig,
    augment_scan,
    decimate_beams,
    drop_points,
    occlude_wedge,
    scan_rings,
    shift_z,
    tilt,
)

REALDATA = Path(__file__).resolve().parent.parent.parent / "shared" / "realdata"
SAMPLE = Path(__file__).resolve().parent.parent / "data" / "samples" / "00" / "velodyne"


def _spinning_scan(elevations_deg, columns=360, rng=None):
    """Rays of a spinning sensor ring by ring, each ring counter-clockwise from azimuth 0,
    hitting a cylinder wall 20 m away; a few returns lost at random."""
    el = np.radians(np.asarray(elevations_deg))[:, None]
    az = np.radians(np.arange(columns) * 360.0 / columns)[None, :]
    r = 20.0 / np.cos(el) * np.ones_like(az)
    pts = np.stack(
        [
            r * np.cos(el) * np.cos(az),
            r * np.cos(el) * np.sin(az),
            r * np.sin(el) * np.ones_like(az),
        ],
        axis=-1,
    ).reshape(-1, 3)
    keep = np.ones(len(pts), bool) if rng is None else rng.random(len(pts)) > 0.05
    return np.column_stack([pts[keep], np.zeros(keep.sum())]).astype(np.float32)


def _elevations(points):
    return np.round(np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))), 3)


def test_rings_come_from_the_firing_order_and_decimation_keeps_every_kth():
    rng = np.random.default_rng(0)
    elevations = np.linspace(15.0, -15.0, 32)
    pts = _spinning_scan(elevations, rng=rng)
    ring = scan_rings(pts)
    assert ring is not None and ring.max() + 1 == 32
    # Each ring holds exactly one elevation: the one fired in that position.
    for k in range(32):
        np.testing.assert_allclose(_elevations(pts[ring == k]), round(elevations[k], 3), atol=2e-3)
    out = decimate_beams(pts, 16, np.random.default_rng(3))
    kept = np.unique(_elevations(out))
    assert len(kept) == 16
    # Every other beam, all of the same parity: spacing twice the sensor's.
    np.testing.assert_allclose(np.diff(np.sort(kept)), 2 * 30.0 / 31, atol=2e-3)
    # A shuffled scan has no firing order: elevation bands instead, about a quarter kept.
    shuffled = pts[rng.permutation(len(pts))]
    assert scan_rings(shuffled) is None
    frac = len(decimate_beams(shuffled, 8)) / len(pts)
    assert 0.15 < frac < 0.35
    # Fewer rings than asked for: unchanged.
    assert len(decimate_beams(pts, 64)) == len(pts)


def test_rings_of_the_bundled_simulated_scan():
    from disco_cli.io.readers import read_scan

    pts = read_scan(SAMPLE / "000000.bin")
    ring = scan_rings(pts)
    assert ring is not None and ring.max() + 1 == 32  # data/samples is HDL-32E


@pytest.mark.skipif(not (REALDATA / "kitti00").is_dir(), reason="no ../shared/realdata")
def test_a_real_kitti_scan_has_64_rings_and_decimates_to_16():
    from disco_cli.io.readers import read_scan

    pts = read_scan(REALDATA / "kitti00" / "velodyne" / "000000.bin")
    ring = scan_rings(pts)
    assert ring is not None and ring.max() + 1 == 64
    out = decimate_beams(pts, 16, np.random.default_rng(0))
    assert scan_rings(out).max() + 1 == 16
    assert 0.15 < len(out) / len(pts) < 0.35


def test_tilt_is_the_rotation_ry_rx():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 4)).astype(np.float32)
    want = Rotation.from_euler("xy", [2.0, -3.0], degrees=True).apply(pts[:, :3])
    got = tilt(pts, 2.0, -3.0)
    np.testing.assert_allclose(got[:, :3], want, atol=1e-5)
    np.testing.assert_array_equal(got[:, 3], pts[:, 3])
    np.testing.assert_allclose(shift_z(pts, -0.4)[:, 2], pts[:, 2] - 0.4, atol=1e-6)


def test_wedge_occlusion_removes_exactly_the_wedge_across_the_seam():
    az = np.radians(np.arange(360) + 0.5)  # one point per degree, away from the edges
    pts = np.column_stack([10 * np.cos(az), 10 * np.sin(az), np.zeros(360), np.zeros(360)])
    out = occlude_wedge(pts.astype(np.float32), 350.0, 20.0)
    left = np.floor(np.degrees(np.arctan2(out[:, 1], out[:, 0])) % 360).astype(int)
    assert len(out) == 340
    assert set(range(350, 360)) | set(range(10)) == set(range(360)) - set(left.tolist())


def test_dropout_keeps_about_the_share_asked_and_augment_is_seeded():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(20000, 4)).astype(np.float32)
    assert abs(len(drop_points(pts, 0.7, rng)) / 20000 - 0.7) < 0.02
    scan = _spinning_scan(np.linspace(10.0, -20.0, 32), rng=rng)
    a = augment_scan(scan, np.random.default_rng(5))
    b = augment_scan(scan, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    # Everything off: the scan itself (a copy).
    off = AugmentConfig(decimate_p=0, drop_p=0, wedge_p=0, tilt_p=0, z_p=0)
    same = augment_scan(scan, np.random.default_rng(5), off)
    np.testing.assert_array_equal(same, scan)
    assert same is not scan


# -- training with augmented copies, on a world that changes -------------------------


def _world(seed: int, n: int = 90) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # Pillars (x, y, radius, height) around a 200 m road along x; the last column marks
    # the static ones (facades, trunks, poles) against things that come and go.
    return np.column_stack(
        [
            rng.uniform(-40, 240, n),
            rng.uniform(-40, 40, n),
            rng.uniform(0.4, 3.0, n),
            rng.uniform(1.0, 12.0, n),
        ]
    )


def _changed(pillars: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """The world after `fraction` of its objects changed: half of those gone, half moved by
    2-6 m and resized; as many new low objects (cars, hedges) appear."""
    out = pillars.copy()
    idx = rng.choice(len(out), size=int(round(fraction * len(out))), replace=False)
    gone, moved = idx[: len(idx) // 2], idx[len(idx) // 2 :]
    ang = rng.uniform(0, 2 * np.pi, len(moved))
    dist = rng.uniform(2.0, 6.0, len(moved))
    out[moved, 0] += dist * np.cos(ang)
    out[moved, 1] += dist * np.sin(ang)
    out[moved, 2:] *= rng.uniform(0.6, 1.4, size=(len(moved), 2))
    new = np.column_stack(
        [
            rng.uniform(-40, 240, len(idx)),
            rng.uniform(-15, 15, len(idx)),
            rng.uniform(0.5, 2.0, len(idx)),
            rng.uniform(1.0, 2.5, len(idx)),
        ]
    )
    return np.concatenate([np.delete(out, gone, axis=0), new])


def _scan(pillars, x, y, yaw, rng):
    pts = []
    for px, py, rad, h in pillars:
        if np.hypot(px - x, py - y) > 45:
            continue
        k = int(60 * rad * h / 4) + 8
        ang = rng.uniform(0, 2 * np.pi, k)
        z = rng.uniform(-1.4, h - 1.5, k)
        pts.append(np.column_stack([px + rad * np.cos(ang), py + rad * np.sin(ang), z]))
    world = np.concatenate(pts)
    world = world[rng.random(len(world)) < 0.8]
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = world[:, 0] - x, world[:, 1] - y
    local = np.column_stack([c * dx + s * dy, -s * dx + c * dy, world[:, 2]])
    local += rng.normal(0, 0.03, local.shape)
    return np.column_stack([local, np.zeros(len(local))]).astype(np.float32)


def write_changed_world(root: Path, seed: int, change: float, scans: int = 40) -> Path:
    """Two sessions of one world, the second driving back 1.5-2.5 m to the side through a
    world in which `change` of the objects changed."""
    base = _world(seed)
    rng = np.random.default_rng(seed + 1)
    world = root / f"world{seed}"
    for name, lateral, heading in (("a", 0.0, 0.0), ("b", 2.0, np.pi)):
        pillars = base if name == "a" else _changed(base, change, rng)
        seq = world / name
        (seq / "velodyne").mkdir(parents=True)
        rows = []
        for i in range(scans):
            x = 5.0 * i + (2.0 if name == "b" else 0.0)
            y = lateral + rng.uniform(-0.5, 0.5)
            yaw = heading + rng.normal(0, 0.3)
            _scan(pillars, x, y, yaw, rng).tofile(seq / "velodyne" / f"{i:06d}.bin")
            c, s = np.cos(yaw), np.sin(yaw)
            rows.append([c, -s, 0, x, s, c, 0, y, 0, 0, 1, 0])
        np.savetxt(seq / "poses.txt", np.array(rows), fmt="%.6f")
    return world


def test_changed_world_changes_the_asked_share():
    rng = np.random.default_rng(0)
    base = _world(4)
    after = _changed(base, 0.3, rng)
    same = (after[:, None, :] == base[None]).all(-1).any(1).sum()
    assert same == len(base) - 27  # 27 of 90 changed: 13 gone, 14 moved
    assert len(after) == len(base) - 13 + 27


@pytest.fixture(scope="module")
def changed(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("changed")
    return write_changed_world(root, 11, 0.4), write_changed_world(root, 12, 0.4)


def test_variants_share_their_scans_pose_and_are_never_anchors(changed):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data

    plain = load_training_data([changed[0]], BEVConfig())
    data = load_training_data([changed[0]], BEVConfig(), variants=2)
    assert len(data) == 3 * len(plain)
    # The original scans, in order, as without variants.
    np.testing.assert_array_equal(data.bevs[data.anchors], plain.bevs)
    np.testing.assert_array_equal(data.xy[data.anchors], plain.xy)
    table = data.variant_table()
    assert table.shape == (len(data), 2)
    for a in data.anchors:
        v = table[a]
        assert np.all(data.source[v] == a)
        np.testing.assert_array_equal(data.xy[v], data.xy[[a, a]])
        np.testing.assert_array_equal(data.heading_deg[v], data.heading_deg[[a, a]])
    copies = np.setdiff1d(np.arange(len(data)), data.anchors)
    assert np.all(table[copies] == -1)
    # Copies differ from their scans (all parts are off for (1 - p) products ~ 4 %).
    differ = [(data.bevs[table[a, 0]] != data.bevs[a]).any() for a in data.anchors]
    assert np.mean(differ) > 0.85


def test_short_training_under_change_beats_the_untrained_network(changed, tmp_path, one_thread):
    from disco_cli.model.bev import BEVConfig
    from disco_cli.training.data import load_training_data

    data = load_training_data([changed[0]], BEVConfig(), variants=1, seed=0)
    held_out = load_training_data([changed[1]], BEVConfig())
    _, before, history, after = short_training(
        data, held_out, tmp_path / "m.pt", 3.0, 40,
        steps=10, val_queries=40, variants=1, augment_p=0.5, occlude_p=0.3,
    )  # fmt: skip
    assert history[-1]["loss"] < history[0]["loss"]
    # On another world, also changed by 40 % between its sessions.
    assert after["recall_at_1"] >= before["recall_at_1"] + 0.2, (before, after)
