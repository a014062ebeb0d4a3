"""KITTI poses: round trip, calibration, malformed files, yaw and ground-truth pairs."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.errors import PoseFileError
from disco_cli.io.poses import (
    gt_pairs,
    gt_pairs_within,
    nearest_distance,
    read_kitti_poses,
    read_times,
    relative_yaw_deg,
    wrap_deg,
    write_kitti_poses,
    xy_yaw,
)


def pose(x: float, y: float, yaw_deg: float, z: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [x, y, z]
    return T


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    T[:, :3, 3] = rng.normal(scale=100.0, size=(n, 3))
    return T


def test_round_trip(tmp_path):
    poses = random_poses(np.random.default_rng(0), 20)
    write_kitti_poses(tmp_path / "poses.txt", poses)
    back = read_kitti_poses(tmp_path / "poses.txt")
    assert back.shape == (20, 4, 4)
    np.testing.assert_allclose(back, poses, rtol=1e-8, atol=1e-9)
    # The file is plain KITTI: 12 numbers per line, row-major 3 x 4.
    first = np.array((tmp_path / "poses.txt").read_text().splitlines()[0].split(), float)
    np.testing.assert_allclose(first, poses[0, :3, :4].ravel(), rtol=1e-8)
    # Writing what was read gives the same bytes (regeneration is byte-identical).
    write_kitti_poses(tmp_path / "again.txt", back)
    assert (tmp_path / "again.txt").read_bytes() == (tmp_path / "poses.txt").read_bytes()


def test_calib_turns_camera_poses_into_lidar_poses(tmp_path):
    # LiDAR (x forward, y left, z up) -> camera (x right, y down, z forward).
    R = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
    t = np.array([0.1, -0.08, -0.27])
    Tr = np.eye(4)
    Tr[:3, :3], Tr[:3, 3] = R, t
    (tmp_path / "calib.txt").write_text(
        "P0: "
        + " ".join(["0"] * 12)
        + "\n"
        + "Tr: "
        + " ".join(f"{v:.6f}" for v in Tr[:3].ravel())
        + "\n"
    )
    # Frame 0: identity. Frame 1: camera 1 m ahead (camera z). Frame 2: camera
    # turned +90 deg about its y axis (which points down).
    cam = np.tile(np.eye(4), (3, 1, 1))
    cam[1, 2, 3] = 1.0
    cam[2, :3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    write_kitti_poses(tmp_path / "poses.txt", cam)
    velo = read_kitti_poses(tmp_path / "poses.txt", calib=tmp_path / "calib.txt")
    np.testing.assert_allclose(velo[0], np.eye(4), atol=1e-9)
    # Forward for the camera is forward (x) for the LiDAR; the mount offset cancels.
    np.testing.assert_allclose(velo[1], pose(1.0, 0.0, 0.0), atol=1e-9)
    # By hand: R^T Ry R = Rz(-90); translation R^T (Ry t - t) = (0.17, 0.37, 0).
    expected = np.eye(4)
    expected[:3, :3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]
    expected[:3, 3] = [0.17, 0.37, 0.0]
    np.testing.assert_allclose(velo[2], expected, atol=1e-9)
    # The calibration may also be given as the matrix itself.
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "poses.txt", calib=Tr), velo, atol=1e-12)


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", 2, "expected 12"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 0 0 1 0 0 0 0 1 0\n", 2, "expected 12"),
        ("1 0 0 0 0 1 0 0 0 0 1 zero\n", 1, "not a number"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", 1, "NaN"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, text, line, what):
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(PoseFileError, match=what) as info:
        read_kitti_poses(path)
    assert str(path) in str(info.value)
    assert f"line {line}" in str(info.value)


def test_missing_empty_and_bad_calib(tmp_path):
    with pytest.raises(PoseFileError, match="no such file"):
        read_kitti_poses(tmp_path / "absent.txt")
    (tmp_path / "empty.txt").write_text("\n")
    with pytest.raises(PoseFileError, match="no poses"):
        read_kitti_poses(tmp_path / "empty.txt")
    write_kitti_poses(tmp_path / "poses.txt", np.eye(4)[None])
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(PoseFileError, match="no 'Tr:' line"):
        read_kitti_poses(tmp_path / "poses.txt", calib=tmp_path / "calib.txt")
    (tmp_path / "times.txt").write_text("0.0\n0.1 0.2\n")
    with pytest.raises(PoseFileError, match="line 2"):
        read_times(tmp_path / "times.txt")


def test_times(tmp_path):
    (tmp_path / "times.txt").write_text("0.000000e+00\n1.0e-01\n0.2\n\n")
    np.testing.assert_allclose(read_times(tmp_path / "times.txt"), [0.0, 0.1, 0.2])


def test_xy_yaw_one_and_stack():
    x, y, yaw = xy_yaw(pose(3.0, -2.0, 120.0))
    assert (x, y) == (3.0, -2.0) and yaw == pytest.approx(np.radians(120.0))
    stack = np.stack([pose(1, 2, -45), pose(-5, 0, 179)])
    xs, ys, yaws = xy_yaw(stack)
    np.testing.assert_allclose(xs, [1, -5])
    np.testing.assert_allclose(ys, [2, 0])
    np.testing.assert_allclose(np.degrees(yaws), [-45, 179])


def test_wrap_deg_interval():
    np.testing.assert_allclose(
        wrap_deg(np.array([180.0, -180.0, 540.0, 181.0, -181.0, 0.0])),
        [180.0, 180.0, 180.0, -179.0, 179.0, 0.0],
    )


def test_relative_yaw_follows_the_convention():
    # A query at heading psi_q, a match at psi_m: yaw = wrap(psi_q - psi_m),
    # wherever they stand.
    rng = np.random.default_rng(1)
    for _ in range(50):
        psi_q, psi_m = rng.uniform(-360, 360, size=2)
        T_match = pose(*rng.normal(size=2) * 50, psi_m)
        got = relative_yaw_deg(T_match, pose(*rng.normal(size=2), psi_q))
        want = (psi_q - psi_m + 180.0) % 360.0 - 180.0
        want = 180.0 if want == -180.0 else want
        assert got == pytest.approx(want, abs=1e-9)
    # The query scan is the match scan rotated by +a (points R(a) p): the query
    # sensor is turned by -a in the match frame.
    a = 30.0
    p_match = np.array([10.0, 0.0, 0.0, 1.0])
    T_query = pose(0, 0, -a)  # sensor turned -a sees the world point at R(+a) p
    np.testing.assert_allclose(
        (np.linalg.inv(T_query) @ p_match)[:2],
        [10 * np.cos(np.radians(a)), 10 * np.sin(np.radians(a))],
        atol=1e-12,
    )
    assert relative_yaw_deg(np.eye(4), T_query) == pytest.approx(-a)


def test_gt_pairs_against_brute_force():
    rng = np.random.default_rng(2)
    a = np.stack([pose(*rng.uniform(0, 30, 2), 0) for _ in range(60)])
    b = np.stack([pose(*rng.uniform(0, 30, 2), 0) for _ in range(40)])
    d = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=-1)
    want = np.argwhere(d <= 4.0)
    np.testing.assert_array_equal(gt_pairs(a, b, 4.0), want)
    dist, idx = nearest_distance(a, b)
    np.testing.assert_allclose(dist, d.min(axis=1))
    np.testing.assert_array_equal(idx, d.argmin(axis=1))


def test_gt_pairs_within_excludes_the_same_pass():
    # A square loop of 40 m sides at 1 m steps: frame 160 returns to frame 0.
    pts = [(i, 0) for i in range(40)] + [(40, i) for i in range(40)]
    pts += [(40 - i, 40) for i in range(40)] + [(0, 40 - i) for i in range(40)] + [(0.5, 0.3)]
    poses = np.stack([pose(x, y, 0) for x, y in pts])
    pairs = gt_pairs_within(poses, radius=3.0, exclude_frames=20)
    assert len(pairs) > 0
    assert np.all(pairs[:, 0] - pairs[:, 1] >= 20)
    # Every revisit involves the loop's end and start, never a neighbour.
    assert set(pairs[:, 0]) <= set(range(150, 161)) and set(pairs[:, 1]) <= set(range(0, 10))
    assert [160, 0] in pairs.tolist()
    times = np.arange(len(poses)) * 0.1
    assert len(gt_pairs_within(poses, 3.0, exclude_frames=1, times=times, exclude_s=30.0)) == 0


def test_real_kitti_calib_gives_lidar_frame(realdata):
    seq = realdata / "kitti00"
    velo = read_kitti_poses(seq / "poses.txt", calib=seq / "calib.txt")
    assert velo.shape == (4541, 4, 4)
    # The car drives forward: the LiDAR's x axis, about 0.86 m per frame at the start.
    step = np.linalg.inv(velo[0]) @ velo[1]
    assert 0.8 < step[0, 3] < 0.9 and abs(step[1, 3]) < 0.1 and abs(step[2, 3]) < 0.1
    # The ground is the LiDAR's x-y plane: heights stay within a few metres over km.
    z = velo[:, 2, 3]
    assert np.ptp(z) < 25 and np.ptp(velo[:, 0, 3]) > 400
    # Sequence 00 revisits its streets; the later frame is the query.
    pairs = gt_pairs_within(velo, radius=3.0, exclude_frames=100)
    assert len(pairs) > 100 and np.all(pairs[:, 0] > pairs[:, 1])
