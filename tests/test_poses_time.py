"""Poses by time: exact matches, interpolation (linear + SLERP) checked against poses
computed independently here, the largest gap, and the KITTI frame-number rule."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.errors import PoseFileError
from disco_cli.io.poses import interpolate_poses, poses_for_scans, slerp, write_kitti_poses


def screw_pose(t: np.ndarray) -> np.ndarray:
    """A vehicle turning at a constant rate about a fixed tilted axis while moving at a
    constant velocity: between any two samples, linear translation and SLERP rotation
    give exactly this motion (Rodrigues' formula, written here without quaternions)."""
    axis = np.array([0.2, -0.1, 1.0])
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.atleast_1d(np.asarray(t, float))
    T = np.tile(np.eye(4), (len(t), 1, 1))
    for i, ti in enumerate(t):
        a = 0.35 * ti  # rad/s
        T[i, :3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        T[i, :3, 3] = [3.0 + 8.0 * ti, -1.0 + 0.5 * ti, 0.2 * ti]
    return T


def test_interpolation_matches_an_independent_motion():
    stamps = np.arange(0.0, 5.01, 0.5)
    times = np.array([0.0, 0.1, 0.25, 1.0, 2.37, 4.99, 5.0])
    P, found = interpolate_poses(stamps, screw_pose(stamps), times)
    assert found.all()
    np.testing.assert_allclose(P, screw_pose(times), atol=1e-9)


def test_slerp_matches_scipy_on_random_rotations():
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(4)
    R = Rotation.random(2, random_state=5)
    s = rng.uniform(0, 1, 20)
    ref = Slerp([0.0, 1.0], R)(s).as_matrix()
    q = R.as_quat()
    from disco_cli.io.poses import quat_to_matrix

    got = quat_to_matrix(slerp(np.tile(q[0], (20, 1)), np.tile(q[1], (20, 1)), s))
    np.testing.assert_allclose(got, ref, atol=1e-10)
    # q and -q are one rotation: the shorter way round is taken either way.
    got_neg = quat_to_matrix(slerp(np.tile(q[0], (20, 1)), np.tile(-q[1], (20, 1)), s))
    np.testing.assert_allclose(got_neg, ref, atol=1e-10)


def test_gap_edges_and_unsorted_stamps():
    stamps = np.array([0.0, 0.1, 0.2, 1.5, 1.6])
    T = screw_pose(stamps)
    times = np.array([-0.05, 0.15, 0.9, 1.55, 1.7, 0.2])
    order = np.array([3, 0, 4, 2, 1])
    P, found = interpolate_poses(stamps[order], T[order], times)  # default gap 0.3 s
    assert found.tolist() == [False, True, False, True, False, True]
    assert np.isnan(P[~found]).all()
    np.testing.assert_allclose(P[5], T[2], atol=0)  # exact: the pose itself
    np.testing.assert_allclose(P[[1, 3]], screw_pose(times[[1, 3]]), atol=1e-9)
    # A larger gap bridges the hole between 0.2 and 1.5 s.
    _, found = interpolate_poses(stamps, T, times, max_gap=1.0)
    assert found.tolist() == [False, True, True, True, False, True]


def write_tum(path, stamps, T):
    from disco_cli.io.poses.tum import write_tum_poses

    write_tum_poses(path, stamps, T)


def test_poses_for_scans_by_time_reports_a_far_scan_once(tmp_path):
    stamps = 1000.0 + np.arange(0, 3.01, 0.1)
    write_tum(tmp_path / "traj.tum", stamps, screw_pose(stamps - 1000.0))
    names = [f"scans/{t:.2f}.bin" for t in (1000.0, 1000.05, 1001.23, 1010.0, 1003.0)]
    P, report = poses_for_scans(names, tmp_path / "traj.tum", poses_format="tum")
    assert report.scans == 5 and report.with_pose == 4 and report.missing == 1
    assert report.exact == 2 and report.interpolated == 2
    assert np.isnan(P[3]).all()
    np.testing.assert_allclose(P[[0, 1, 2, 4]], screw_pose(np.array([0, 0.05, 1.23, 3.0])),
                               atol=1e-6)  # fmt: skip
    line = report.warning()
    assert line.count("\n") == 0 and "1 of 5 scans have no pose" in line
    assert "1010.00.bin" in line and str(tmp_path / "traj.tum") in line
    # Times may be given as numbers, as a bag's message stamps are.
    P2, r2 = poses_for_scans(np.array([1000.05, 1020.0]), tmp_path / "traj.tum")
    np.testing.assert_allclose(P2[0], P[1])
    assert r2.missing == 1 and "t=1020" in r2.warning()
    # A gap set by hand: 0.01 s leaves the interpolated scans without a pose.
    _, r3 = poses_for_scans(names, tmp_path / "traj.tum", max_time_gap=0.01)
    assert r3.with_pose == 2 and r3.missing == 3


def test_nclt_scans_by_utime(tmp_path):
    from disco_cli.io.poses.nclt import body_to_velo, write_nclt_poses

    utime = 1328388850000000 + 100_000 * np.arange(20)
    T = screw_pose((utime - utime[0]) * 1e-6)
    write_nclt_poses(tmp_path / "groundtruth_2012-02-04.csv", utime, T)
    scans = [f"velodyne_sync/{u}.bin" for u in (utime[3], utime[3] + 50_000, utime[-1] + 10**6)]
    P, report = poses_for_scans(scans, tmp_path / "groundtruth_2012-02-04.csv")
    assert report.format == "nclt" and report.missing == 1
    X = np.diag([1.0, -1.0, -1.0, 1.0])  # NCLT's z down -> z up, world and LiDAR
    want = X @ screw_pose(np.array([0.3, 0.35])) @ body_to_velo() @ X
    np.testing.assert_allclose(P[:2], want, atol=1e-9)


def test_kitti_rule_rows_by_frame_number(tmp_path):
    T = screw_pose(np.arange(50) * 0.1)
    write_kitti_poses(tmp_path / "poses.txt", T)
    # All scans: row i. A part of the sequence: rows by the frame number in the name.
    P, r = poses_for_scans([f"{i:06d}.bin" for i in range(50)], tmp_path / "poses.txt")
    np.testing.assert_allclose(P, T, atol=1e-8)
    assert r.max_time_gap is None
    P, r = poses_for_scans(["v/000007.bin", "v/000042.bin"], tmp_path / "poses.txt")
    np.testing.assert_allclose(P, T[[7, 42]], atol=1e-8)
    # A frame beyond the file gets no pose and is reported; a name without a number is
    # an error, since no row can be picked for it.
    P, r = poses_for_scans(["000003.bin", "000077.bin"], tmp_path / "poses.txt")
    assert r.missing == 1 and np.isnan(P[1]).all() and "000077.bin" in r.warning()
    with pytest.raises(PoseFileError, match="no frame number"):
        poses_for_scans(["a.bin", "b.bin"], tmp_path / "poses.txt")
    # Numbers are frame numbers for KITTI poses (they hold no times).
    P, r = poses_for_scans(np.array([7, 42, 99]), tmp_path / "poses.txt")
    np.testing.assert_allclose(P[:2], T[[7, 42]], atol=1e-8)
    assert r.missing == 1 and "frame 99" in r.warning()
    # Fewer rows than scans: not this sequence's file.
    with pytest.raises(PoseFileError, match="50 poses for 60 scans"):
        poses_for_scans([f"{i:06d}.bin" for i in range(60)], tmp_path / "poses.txt")


def test_kitti360_scans_by_frame_number_with_gaps(tmp_path):
    from disco_cli.io.poses import find_pose_file

    frames = np.array([0, 1, 2, 3, 10, 11])  # the vehicle stood still over frames 4-9
    T = screw_pose(frames * 0.1)
    seq = tmp_path / "data_poses" / "drive"
    seq.mkdir(parents=True)
    rows = [f"{f} " + " ".join(f"{v:.17g}" for v in Ti[:3, :4].ravel()) for f, Ti in zip(frames, T)]
    (seq / "poses.txt").write_text("\n".join(rows) + "\n")
    scans = [f"data/{f:010d}.bin" for f in (1, 2, 6, 11)]
    P, report = poses_for_scans(scans, seq / "poses.txt", calib="none")
    assert report.format == "kitti360" and report.missing == 1  # frame 6: a 0.7 s gap
    np.testing.assert_allclose(P[[0, 1, 3]], T[[1, 2, 5]], atol=1e-12)
    P, report = poses_for_scans(scans, seq / "poses.txt", calib="none", max_time_gap=1.0)
    assert report.missing == 0 and report.interpolated == 1
    np.testing.assert_allclose(P[2], screw_pose(np.array([0.6]))[0], atol=1e-9)
    # The NCLT download layout: ground_truth/ beside the session folders.
    (tmp_path / "ground_truth").mkdir()
    (tmp_path / "ground_truth" / "groundtruth_2012-02-04.csv").write_text("1,0,0,0,0,0,0\n")
    (tmp_path / "2012-02-04").mkdir()
    assert find_pose_file(tmp_path / "2012-02-04").name == "groundtruth_2012-02-04.csv"
