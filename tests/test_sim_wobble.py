"""`disco simulate --wobble`: every session's platform rolls and pitches from scan to scan.

Truth: the ground. Rays cast from a tilted sensor see the ground plane tilted in the
sensor's frame by exactly the recorded tilt, so the plane fitted to a wobbled scan's
ground points, turned into the world by the recorded pose, must be the level scan's.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from disco_cli.io.poses import read_kitti_poses
from disco_cli.io.readers import read_scan
from disco_cli.simulator import simulate
from disco_cli.simulator.session import wobble


def ground_normal(points: np.ndarray, mount: float) -> np.ndarray:
    """Unit normal (z up) of the plane fitted to the points near the ground, 4-15 m out."""
    r = np.hypot(points[:, 0], points[:, 1])
    near = points[(r > 4) & (r < 15) & (np.abs(points[:, 2] + mount) < 1.5)][:, :3]
    # Keep the lowest points of each 1 m cell: the ground, not kerbs or cars.
    cells = np.floor(near[:, :2]).astype(int)
    order = np.lexsort((near[:, 2], cells[:, 1], cells[:, 0]))
    near, cells = near[order], cells[order]
    first = np.ones(len(near), bool)
    first[1:] = np.any(cells[1:] != cells[:-1], axis=1)
    low = near[first]
    centred = low - low.mean(axis=0)
    n = np.linalg.svd(centred, full_matrices=False)[2][-1]
    return n if n[2] > 0 else -n


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def test_wobble_stays_within_bound_and_changes_smoothly():
    rots = wobble(2000, 4.0, [1, 31, 0])
    roll = np.degrees(np.arctan2(rots[:, 2, 1], rots[:, 2, 2]))
    pitch = np.degrees(-np.arcsin(rots[:, 2, 0]))
    assert np.abs(roll).max() <= 4.0 + 1e-9 and np.abs(pitch).max() <= 4.0 + 1e-9
    assert 1.0 < roll.std() < 3.0 and 1.0 < pitch.std() < 3.0
    # Neighbouring scans lean alike (AR(1), 0.6), far ones do not.
    assert 0.45 < np.corrcoef(roll[1:], roll[:-1])[0, 1] < 0.75
    assert abs(np.corrcoef(roll[10:], roll[:-10])[0, 1]) < 0.15


@pytest.mark.slow
def test_wobbled_scans_see_the_ground_tilted_by_the_recorded_pose(tmp_path):
    level, wobbled = tmp_path / "level", tmp_path / "wobbled"
    kw = dict(sessions=1, frames=12, step_m=1.0, sensor="hdl32", seed=5, threads=2)
    simulate(level, **kw)
    simulate(wobbled, wobble_deg=5.0, **kw)
    assert json.loads((wobbled / "world.json").read_text())["wobble_deg"] == 5.0
    mount = json.loads((level / "world.json").read_text())["sensor"]["mount_height"]
    p_level = read_kitti_poses(level / "00" / "poses.txt")
    p_wob = read_kitti_poses(wobbled / "00" / "poses.txt")
    # Same stations: the wobble turns the sensor, it does not move it.
    np.testing.assert_allclose(p_wob[:, :3, 3], p_level[:, :3, 3], atol=1e-9)
    leans = []
    for i in range(len(p_level)):
        n_level = ground_normal(read_scan(level / "00" / "velodyne" / f"{i:06d}.bin"), mount)
        n_wob = ground_normal(read_scan(wobbled / "00" / "velodyne" / f"{i:06d}.bin"), mount)
        # In the world (each turned by its recorded pose) the two grounds are one plane ...
        assert angle_deg(p_wob[i, :3, :3] @ n_wob, p_level[i, :3, :3] @ n_level) < 0.6
        # ... while the wobbled sensor sees it leaning.
        leans.append(angle_deg(n_wob, n_level))
    assert max(leans) > 3.0  # the check above is not vacuous
