"""Motion distortion at a car's speed: places sampled 5 m apart are not a car doing 50 m/s.

Truth: a straight, steady drive, where a sweep's start and end are the scan's pose moved
back and forth by half the distance driven in one sweep.
"""

from __future__ import annotations

import numpy as np

from disco_cli.simulator import sweep_poses
from disco_cli.simulator.session import MAX_SWEEP_SPEED


def steady(step: float, n: int = 6) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = step * np.arange(n)
    return poses


def test_a_sweep_spans_one_step_by_default_and_a_fraction_of_it_when_asked():
    poses = steady(5.0)
    starts, ends = sweep_poses(poses)
    np.testing.assert_allclose(ends[:, 0, 3] - starts[:, 0, 3], 5.0)
    fraction = MAX_SWEEP_SPEED / 10.0 / 5.0  # 10 Hz, places 5 m apart
    starts, ends = sweep_poses(poses, fraction)
    np.testing.assert_allclose(ends[:, 0, 3] - starts[:, 0, 3], MAX_SWEEP_SPEED / 10.0)
    # Centred on the scan's own pose.
    np.testing.assert_allclose((starts[:, 0, 3] + ends[:, 0, 3]) / 2, poses[:, 0, 3])
