"""The calibrated families of the paper's table (issue 31).

Truths: the Oxford-like submap against the simulator's flat ground and its own count;
the ground-truth lag against a hand-shifted pose; and a short calibration check, where
Scan Context on a small world of each family must fall in the band that says the world is
as hard as the paper's data (its Recall@1 there: 0.636 / 0.526 / 0.646), not as easy as
the suite it replaced (0.98-1.00).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from disco_cli.evaluation.paper_families import (
    FAMILIES,
    GROUND_ABOVE_M,
    SEEDS,
    SUBMAP_POINTS,
    evaluate,
    submap,
    summarize,
)
from disco_cli.simulator import simulate


def test_seed_sets_are_disjoint():
    sets = [set(v) for v in SEEDS.values()]
    assert sum(len(s) for s in sets) == len(set().union(*sets))


def test_submap_drops_the_ground_and_keeps_4096_points_within_the_crop():
    rng = np.random.default_rng(0)
    mount = 1.8
    ground = np.c_[rng.uniform(-60, 60, (20000, 2)), np.full(20000, -mount), np.ones(20000)]
    walls = np.c_[rng.uniform(-60, 60, (8000, 2)), rng.uniform(-1.0, 6.0, 8000), np.ones(8000)]
    pts = np.vstack([ground, walls]).astype(np.float32)
    out = submap(pts, mount, seed=1, crop_m=50.0)
    assert out.shape == (SUBMAP_POINTS, 4)
    assert (out[:, 2] > -mount + GROUND_ABOVE_M).all()  # no ground point left
    assert (np.hypot(out[:, 0], out[:, 1]) <= 50.0).all()
    # Drawn from the walls within the crop, without repeats while there are enough.
    assert len(np.unique(out, axis=0)) == SUBMAP_POINTS
    np.testing.assert_array_equal(out, submap(pts, mount, seed=1, crop_m=50.0))


def small(name: str):
    """A small world of each family: shorter runs, the same kind of place and change."""
    lengths = {"nclt": 300.0, "mulran": 1000.0, "oxford": 2000.0}
    return replace(FAMILIES[name], length_m=lengths[FAMILIES[name].name])


def write_world(tmp_path, fam, seed: int):
    from disco_cli.simulator import ChangeParams, RobotParams, TownParams

    folder = tmp_path / f"{fam.name}-{seed}"
    params = TownParams(style=fam.style, change=ChangeParams(fraction=fam.change))
    robot = RobotParams(offset_m=fam.offset_m, jitter_m=fam.jitter_m)
    simulate(
        folder,
        sessions=2,
        length_m=fam.length_m,
        step_m=fam.step_m,
        sensor=fam.sensor,
        seed=seed,
        threads=2,
        params=params,
        robot=robot,
        motion_distortion=fam.motion_distortion,
        wobble_deg=fam.wobble_deg,
    )
    return folder


def test_the_ground_truth_lag_moves_the_query_run_back_along_its_track(tmp_path):
    fam = replace(small("oxford"), length_m=200.0)
    folder = write_world(tmp_path, fam, 8611)
    plain = evaluate(fam, folder, "spectral")
    lagged = evaluate(replace(fam, gt_lag_m=30.0), folder, "spectral")
    # A 30 m lag beyond the 25 m radius: queries that had their place lose it.
    assert sum(r["r1"] for r in lagged) < sum(r["r1"] for r in plain)
    assert [r["d1"] for r in lagged] == [r["d1"] for r in plain]  # the scans are the same


@pytest.mark.slow
# MulRan-like as it was calibrated: scored with the query run's ground truth 1.75 m behind
# its scans (the table's head now scores without the lag; Scan Context there: 0.84).
@pytest.mark.parametrize("name", ["nclt", "mulran_lagged", "oxford"])
def test_scan_context_is_as_hard_pressed_as_on_the_papers_data(tmp_path, name):
    fam = small(name)
    folder = write_world(tmp_path, fam, SEEDS["calibration"][0])
    assert json.loads((folder / "world.json").read_text())["seed"] == SEEDS["calibration"][0]
    s = summarize(evaluate(fam, folder, "scancontext"))
    assert s["queries"] >= 40
    assert BANDS[name][0] <= s["r1"] <= BANDS[name][1], s


# Scan Context's Recall@1 on the small worlds above (measured 2026-11-28 on seed 8611:
# 0.684 / 0.611 / 0.562): within about 0.2 of the paper's figure for the dataset, the band
# leaning up as the small maps have fewer places to confuse; never near the 0.98-1.00 of
# the suite these families replaced.
BANDS = {"nclt": (0.45, 0.85), "mulran_lagged": (0.35, 0.75), "oxford": (0.45, 0.85)}
