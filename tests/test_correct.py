"""`disco correct` and its pose graph (disco_cli/graph): odometry and loops in, the
drift out.

Truths are independent of the code under test: a square drive built here from its
corners, its loops' relative poses taken from those true poses, and a simulated
world's own poses.txt. The graph needs gtsam (the [graph] extra, in [test]).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from disco_cli.cli import app
from disco_cli.evaluation.trajectory import align_planar, ate, rpe
from disco_cli.io.poses import read_kitti_poses, read_times, write_kitti_poses
from disco_cli.io.poses.tum import read_tum_poses, write_tum_poses
from disco_cli.simulator.odometry_drift import Drift, drift_odometry

gtsam = pytest.importorskip("gtsam", reason="the [graph] extra (gtsam) is not installed")

from disco_cli.graph.pose_graph import PoseGraph  # noqa: E402

SIDE = 20  # metres, one pose a metre
LAPS = 2


def square_drive(side: int = SIDE, laps: int = LAPS) -> np.ndarray:
    """True poses `[4 * side * laps, 4, 4]`: round a square of `side` metres
    anticlockwise from the origin, heading along each side, `laps` times."""
    poses = []
    for _ in range(laps):
        for edge in range(4):
            heading = edge * math.pi / 2
            corner = {0: (0, 0), 1: (side, 0), 2: (side, side), 3: (0, side)}[edge]
            for k in range(side):
                T = np.eye(4)
                c, s = math.cos(heading), math.sin(heading)
                T[:2, :2] = [[c, -s], [s, c]]
                T[:2, 3] = corner[0] + k * c, corner[1] + k * s
                poses.append(T)
    return np.stack(poses)


def true_loops(truth: np.ndarray, lap: int) -> list[tuple[int, int, np.ndarray]]:
    """Each scan of the second lap closes a loop with the same place on the first."""
    return [(i - lap, i, np.linalg.inv(truth[i - lap]) @ truth[i]) for i in range(lap, len(truth))]


# 0.2 degrees of yaw a step: 16 degrees a lap, the far corner 6 m out in the odometry.
DRIFT = Drift(scale=0.02, yaw_bias_deg=0.2, noise_m=0.01, noise_deg=0.05, seed=3)


def corrected(odometry: np.ndarray, loops: list, kernel: str = "cauchy") -> object:
    graph = PoseGraph(odometry, kernel=kernel)
    for j, i, T in loops:
        graph.add_loop(j, i, T, fitness=0.7, rmse=0.05)
    return graph.optimize()


def corner_errors(poses: np.ndarray, truth: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """How far each corner is from the truth's after a planar rigid alignment (the
    loops say where the laps meet, not which way the whole square is turned)."""
    A = align_planar(poses, truth)
    return np.linalg.norm((A @ poses)[corners, :3, 3] - truth[corners, :3, 3], axis=1)


def test_a_square_drive_with_drift_comes_back_to_its_corners():
    truth = square_drive()
    odo = drift_odometry(truth, DRIFT)
    corners = np.arange(0, len(truth), SIDE)  # every corner, both laps
    assert np.linalg.norm(odo[corners, :3, 3] - truth[corners, :3, 3], axis=1).max() > 5.0
    assert corner_errors(odo, truth, corners).max() > 2.0
    result = corrected(odo, true_loops(truth, 4 * SIDE))
    # Stated tolerance: every corner within 0.5 m of the truth after the alignment (the
    # 2 % scale error, which loops cannot see, puts the far corner 0.57 m out alone).
    errors = corner_errors(result.poses, truth, corners)
    assert errors.max() < 0.5, errors
    # The laps meet: each corner of lap 2 within 5 cm of lap 1's.
    lap = 4 * SIDE
    laps = result.poses[corners, :3, 3]
    assert np.linalg.norm(laps[4:] - laps[:4], axis=1).max() < 0.05
    assert not result.down_weighted
    assert ate(result.poses, truth) < 0.2 * ate(odo, truth)
    # Headings: each pose of lap 2 turned as lap 1's within 3 degrees (a loop's
    # rotation sigma is 1 degree; the odometry leans on it with 0.2 degrees a step).
    yaw = np.arctan2(result.poses[:, 1, 0], result.poses[:, 0, 0])
    turn = np.degrees(np.angle(np.exp(1j * (yaw[lap:] - yaw[:-lap]))))
    assert np.abs(turn).max() < 3.0


@pytest.mark.parametrize("kernel", ["cauchy", "gnc"])
def test_a_false_loop_is_down_weighted_and_its_residual_reported(kernel):
    truth = square_drive()
    odo = drift_odometry(truth, DRIFT)
    loops = true_loops(truth, 4 * SIDE)
    # Scan 130 (second lap, third side) "seen" from scan 10 (first side, 20 m away)
    # as if it stood there: a false loop.
    false = (10, 130, np.eye(4))
    clean = corrected(odo, loops, kernel)
    fooled = corrected(odo, loops + [false], kernel)
    flagged = [lp for lp in fooled.down_weighted]
    assert [(lp.match, lp.query) for lp in flagged] == [(10, 130)]
    assert flagged[0].residual > 10.0 and flagged[0].weight < 0.1
    assert flagged[0].translation_m > 10.0  # it asked for a 20 m jump
    assert ate(fooled.poses, truth) <= 1.2 * ate(clean.poses, truth) + 0.02
    # Without a robust kernel the same loop folds the square.
    plain = corrected(odo, loops + [false], "none")
    assert ate(plain.poses, truth) > 3 * ate(clean.poses, truth)


def test_loops_on_one_side_take_the_heading_drift_out_of_the_whole_drive():
    # Three laps, loops only along lap 2's first side: the graph alone bends the drive
    # there and leaves lap 3 to drift; fitted to those loops, the heading drift
    # (0.2 degrees a step of 1 m: 0.2 degrees a metre) comes out everywhere.
    truth = square_drive(laps=3)
    odo = drift_odometry(truth, DRIFT)
    lap = 4 * SIDE
    few = [lp for lp in true_loops(truth, lap) if lap <= lp[1] < lap + SIDE]
    plain = PoseGraph(odo, drift=False)
    fitted = PoseGraph(odo)
    for j, i, T in few:
        plain.add_loop(j, i, T, fitness=0.7, rmse=0.05)
        fitted.add_loop(j, i, T, fitness=0.7, rmse=0.05)
    a, b = plain.optimize(), fitted.optimize()
    assert a.yaw_drift_deg_per_m == 0.0
    assert b.yaw_drift_deg_per_m == pytest.approx(DRIFT.yaw_bias_deg, abs=0.02)
    assert ate(a.poses, truth) > 1.5  # lap 3 out by metres (2.1 m)
    assert ate(b.poses, truth) < 0.3 * ate(a.poses, truth)
    assert not b.down_weighted


def test_without_loops_no_pose_moves():
    truth = square_drive(laps=1)
    odo = drift_odometry(truth, DRIFT)
    result = PoseGraph(odo).optimize()
    assert np.abs(result.moved_m).max() < 1e-6
    assert result.loops == ()


def test_trajectory_errors_against_hand_figures():
    truth = square_drive(laps=1)
    # Turned by 30 degrees and shifted: ATE aligns it away.
    A = np.eye(4)
    A[:2, :2] = [[math.cos(0.5), -math.sin(0.5)], [math.sin(0.5), math.cos(0.5)]]
    A[:3, 3] = [5.0, -3.0, 1.0]
    moved = A @ truth
    assert ate(moved, truth) < 1e-9
    np.testing.assert_allclose(align_planar(moved, truth) @ A, np.eye(4), atol=1e-9)
    # Every position 0.3 m off along z... after alignment, 0; 0.3 m along x on odd
    # poses only: an RMS of 0.15 m about the mean shift.
    off = truth.copy()
    off[1::2, 0, 3] += 0.3
    assert ate(off, truth) == pytest.approx(0.15, abs=0.01)
    t, r = rpe(off, truth)
    assert t == pytest.approx(0.3, abs=1e-9) and r == pytest.approx(0.0, abs=1e-6)


# -- the command line, on a tiny simulated world ---------------------------------------


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 30-scan session 2 m apart: its loop is longer than 60 m, so it never comes
    back to where it was (no revisit), with drifted odometry beside poses.txt."""
    out = tmp_path_factory.mktemp("tiny") / "sim"
    args = ["simulate", str(out), "--sessions", "1", "--frames", "30", "--step-m", "2"]
    args += ["--seed", "11", "--odometry-drift", "0.02,0.1", "--threads", "2", "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return out / "00"


def _correct(*args: object) -> object:
    return CliRunner().invoke(app, ["correct", *map(str, args)])


def test_simulate_writes_drifted_odometry_beside_the_truth(tiny_world: Path):
    truth = read_kitti_poses(tiny_world / "poses.txt")
    odo = read_kitti_poses(tiny_world / "odometry.txt")
    assert odo.shape == truth.shape
    np.testing.assert_allclose(odo[0], truth[0], atol=1e-8)
    steps_t = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    steps_o = np.linalg.norm(np.diff(odo[:, :3, 3], axis=0), axis=1)
    assert np.median(steps_o / steps_t) == pytest.approx(1.02, abs=0.01)  # the scale error


def test_kitti_in_kitti_out_and_no_revisit_moves_nothing(tiny_world: Path, tmp_path: Path):
    out, loops = tmp_path / "corrected.txt", tmp_path / "loops.g2o"
    res = _correct(
        tiny_world, "--odometry", tiny_world / "odometry.txt", "-o", out,
        "--gt", tiny_world / "poses.txt", "--exclude-frames", "10", "--loops-out", loops,
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    odo = read_kitti_poses(tiny_world / "odometry.txt")
    got = read_kitti_poses(out)
    assert got.shape == odo.shape
    # No revisit: every pose moved by less than 1 cm.
    assert np.linalg.norm(got[:, :3, 3] - odo[:, :3, 3], axis=1).max() < 0.01
    assert "ATE" in res.output and "RPE" in res.output
    assert f"{out}: 30 poses written (kitti)" in res.output
    assert loops.is_file()


def test_tum_in_tum_out(tiny_world: Path, tmp_path: Path):
    stamps = read_times(tiny_world / "times.txt") + 1000.0
    times = tmp_path / "times.txt"
    times.write_text("".join(f"{t:.6f}\n" for t in stamps))
    odo_tum = tmp_path / "odom.tum"
    write_tum_poses(odo_tum, stamps, read_kitti_poses(tiny_world / "odometry.txt"))
    out = tmp_path / "corrected.tum"
    res = _correct(
        tiny_world, "--odometry", odo_tum, "-o", out, "--times", times, "--exclude-frames", "10"
    )
    assert res.exit_code == 0, res.output
    t_in, p_in = read_tum_poses(odo_tum)
    t_out, p_out = read_tum_poses(out)
    np.testing.assert_allclose(t_out, t_in, atol=1e-6)
    np.testing.assert_allclose(p_out, p_in, atol=0.01)
    assert "(tum)" in res.output


def test_bad_odometry_is_one_line_naming_the_file(tiny_world: Path, tmp_path: Path):
    short = tmp_path / "short.txt"
    write_kitti_poses(short, read_kitti_poses(tiny_world / "odometry.txt")[:5])
    for odo, words in [(short, "5 poses for 30 scans"), (tmp_path / "none.txt", "none.txt")]:
        res = _correct(tiny_world, "--odometry", odo, "-o", tmp_path / "out.txt")
        assert res.exit_code != 0
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and "Traceback" not in res.output, res.output
        assert words in lines[0] and str(odo.name) in lines[0], lines
    assert not (tmp_path / "out.txt").exists()


def test_without_gtsam_one_line_naming_the_extra(
    tiny_world: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setitem(sys.modules, "gtsam", None)  # `import gtsam` raises ImportError
    res = _correct(tiny_world, "--odometry", tiny_world / "odometry.txt", "-o", tmp_path / "o.txt")
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "disco-cli[graph]" in lines[0], res.output
    assert not (tmp_path / "o.txt").exists()


def test_real_kitti_frames_without_a_revisit_come_back_unmoved(realdata: Path, tmp_path: Path):
    # KITTI 00's 12 frames (0-10 and 15): a drive with no revisit. There is no KISS-ICP
    # run beside them, so the odometry is the ground truth itself, put in the LiDAR's
    # frame by the README's formula T_velo = inv(Tr) @ P @ Tr (written out here, not
    # disco's own calibration code). Twelve scans lie within disco loops' default
    # 50-scan window, so no pair is a candidate: what is checked is the real folder read
    # end to end (frame 15 after 10), KITTI in and out, and a graph without loops.
    seq = realdata / "kitti00"
    calib = {
        ln.split(":")[0]: np.array(ln.split(":")[1].split(), dtype=np.float64)
        for ln in (seq / "calib.txt").read_text().splitlines()
        if ":" in ln
    }
    Tr = np.vstack([calib["Tr"].reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    rows = np.loadtxt(seq / "poses_present_frames.txt")
    P = np.tile(np.eye(4), (len(rows), 1, 1))
    P[:, :3, :] = rows[:, 1:].reshape(-1, 3, 4)
    lidar = np.linalg.inv(Tr) @ P @ Tr
    odo = tmp_path / "odometry.txt"
    np.savetxt(odo, lidar[:, :3, :].reshape(len(lidar), 12), fmt="%.9f")
    out = tmp_path / "corrected.txt"
    res = _correct(seq, "--odometry", odo, "-o", out, "--loops-out", tmp_path / "loops.csv")
    assert res.exit_code == 0, res.output
    got = read_kitti_poses(out)
    assert got.shape == (12, 4, 4)
    assert np.linalg.norm(got[:, :3, 3] - lidar[:, :3, 3], axis=1).max() < 0.01
    assert "0 loops in the graph (0 found among 12 scans)" in res.output
    assert f"{out}: 12 poses written (kitti)" in res.output
