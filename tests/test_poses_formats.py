"""Pose file formats: each written here from known poses and read back to the same 4 x 4;
the format guessed from names and content; the published extrinsics; an Oxford submap."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.errors import DiscoError, PoseFileError
from disco_cli.io.poses import guess_poses_format, read_poses


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def known_poses(n: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Poses built from roll, pitch, yaw by explicit products (the test's own truth)."""
    rng = np.random.default_rng(seed)
    rpy = np.c_[rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n)]
    T = np.tile(np.eye(4), (n, 1, 1))
    for i, (r, p, y) in enumerate(rpy):
        T[i, :3, :3] = rot_z(y) @ rot_y(p) @ rot_x(r)
    T[:, :3, 3] = rng.normal(scale=50.0, size=(n, 3))
    return T, rpy


def test_tum_round_trip(tmp_path):
    T, _ = known_poses()
    t = 1317384506.4 + 0.1 * np.arange(len(T))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # x, y, z, w: an independent converter
    for ti, Ti, qi in zip(t, T, q):
        lines.append(f"{ti:.6f} " + " ".join(f"{v:.12g}" for v in [*Ti[:3, 3], *qi]))
    (tmp_path / "traj.txt").write_text("\n".join(lines) + "\n")
    assert guess_poses_format(tmp_path / "traj.txt") == "tum"
    keys, back, fmt, _ = read_poses(tmp_path / "traj.txt")
    assert fmt == "tum"
    np.testing.assert_allclose(keys, t, atol=1e-6)
    np.testing.assert_allclose(back, T, atol=1e-9)


def test_nclt_roll_pitch_yaw_and_body_to_velodyne(tmp_path):
    T, rpy = known_poses()
    utime = 1328388850000000 + 100_000 * np.arange(len(T))
    rows = ["nan,nan,nan,nan,nan,nan,nan"]  # NCLT files open with unknown rows
    rows += [
        f"{u},{x:.17g},{y:.17g},{z:.17g},{r:.17g},{p:.17g},{yw:.17g}"
        for u, (x, y, z), (r, p, yw) in zip(utime, T[:, :3, 3], rpy)
    ]
    path = tmp_path / "groundtruth_2012-02-04.csv"
    path.write_text("\n".join(rows) + "\n")
    assert guess_poses_format(path) == "nclt"
    keys, body, fmt, _ = read_poses(path, calib="none")
    np.testing.assert_allclose(keys, utime * 1e-6, rtol=0, atol=1e-6)
    np.testing.assert_allclose(body, T, atol=1e-12)
    # By default the Velodyne's pose: body pose times NCLT's published x_body_velo
    # (0.002, -0.004, -0.957 m; roll 0.807, pitch 0.166, yaw -90.703 deg), with sensor
    # and world turned 180 degrees about x (z up, as the nclt scan reader returns points).
    E = np.eye(4)
    E[:3, :3] = rot_z(np.radians(-90.703)) @ rot_y(np.radians(0.166)) @ rot_x(np.radians(0.807))
    E[:3, 3] = [0.002, -0.004, -0.957]
    X = np.diag([1.0, -1.0, -1.0, 1.0])
    _, velo, _, frame = read_poses(path)
    np.testing.assert_allclose(velo, X @ T @ E @ X, atol=1e-12)
    assert "x_body_velo" in frame


def test_nclt_relative_poses_map_returned_points_onto_each_other(tmp_path):
    """Two NCLT scans of one world, written in NCLT's encoding (z-down Velodyne frame)
    with body poses in NCLT's z-down world: the relative transform of the returned
    (z-up) poses maps the returned points of one scan onto those of the other."""
    from disco_cli.io.poses import poses_for_scans
    from disco_cli.io.poses.nclt import body_to_velo, write_nclt_poses
    from disco_cli.io.readers import read_scan

    rng = np.random.default_rng(5)
    # NCLT's z-down world: ground-like points 0.5 to 1.5 m below the body origin (1,200:
    # a .bin is read as a scan from 1,000 points, io/readers/plausible.py).
    world = np.c_[rng.uniform(-40, 40, (1200, 2)), rng.uniform(0.5, 1.5, 1200)]
    body = np.tile(np.eye(4), (2, 1, 1))
    body[0, :3, :3] = rot_z(0.3) @ rot_y(0.02) @ rot_x(-0.03)
    body[0, :3, 3] = [2.0, -1.0, -0.2]
    body[1, :3, :3] = rot_z(1.4) @ rot_y(-0.04) @ rot_x(0.05)
    body[1, :3, 3] = [6.0, 3.0, 0.1]
    velo = body @ body_to_velo()  # T_world<-velodyne, NCLT's own frames
    folder = tmp_path / "2012-02-04" / "velodyne_sync"
    folder.mkdir(parents=True)
    utimes = [1328388850000000, 1328388850100000]
    for u, V in zip(utimes, velo):
        local = (np.c_[world, np.ones(len(world))] @ np.linalg.inv(V).T)[:, :3]
        raw = np.round((local + 100.0) / 0.005).astype("<u2")
        rec = np.zeros(len(raw), dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"),
                                        ("i", "u1"), ("l", "u1")])  # fmt: skip
        rec["x"], rec["y"], rec["z"] = raw.T
        rec.tofile(folder / f"{u}.bin")
    write_nclt_poses(tmp_path / "2012-02-04" / "groundtruth_2012-02-04.csv", utimes, body)
    scans = [folder / f"{u}.bin" for u in utimes]
    P, report = poses_for_scans(scans, tmp_path / "2012-02-04" / "groundtruth_2012-02-04.csv")
    assert report.missing == 0
    a, b = (read_scan(s)[:, :3].astype(np.float64) for s in scans)
    rel = np.linalg.inv(P[0]) @ P[1]  # scan 1's frame -> scan 0's frame
    np.testing.assert_allclose(b @ rel[:3, :3].T + rel[:3, 3], a, atol=0.01)
    # Both scans see those points below the sensor: z < 0 (z up).
    assert np.median(a[:, 2]) < 0 and np.median(b[:, 2]) < 0


def test_mulran_nanoseconds_and_ouster_extrinsic(tmp_path):
    T, _ = known_poses()
    stamps = 1566535751292145922 + 100_000_000 * np.arange(len(T), dtype=np.int64)
    rows = [f"{s}," + ",".join(f"{v:.17g}" for v in Ti[:3, :4].ravel()) for s, Ti in zip(stamps, T)]
    path = tmp_path / "global_pose.csv"
    path.write_text("\n".join(rows) + "\n")
    assert guess_poses_format(path) == "mulran"
    keys, base, _, _ = read_poses(path, calib="none")
    np.testing.assert_allclose(base, T, atol=1e-12)
    # Nanosecond stamps 0.1 s apart stay 0.1 s apart (to well under a microsecond).
    np.testing.assert_allclose(np.diff(keys), 0.1, atol=1e-6)
    E = np.eye(4)
    E[:3, :3] = rot_z(np.radians(179.6654)) @ rot_y(np.radians(0.0003)) @ rot_x(np.radians(0.0001))
    E[:3, 3] = [1.7042, -0.021, 1.8047]
    _, ouster, _, _ = read_poses(path)
    np.testing.assert_allclose(ouster, T @ E, atol=1e-12)


def test_oxford_locations_and_submap(tmp_path):
    from disco_cli.io.readers import list_scans, read_scan

    run = tmp_path / "oxford" / "2014-05-19-13-20-57"
    (run / "pointcloud_20m").mkdir(parents=True)
    stamps = [1400505893134088, 1400505894395159]
    ne = [(5735712.77, 620084.40), (5735700.12, 620090.55)]
    text = "timestamp,northing,easting\n" + "".join(
        f"{t},{n},{e}\n" for t, (n, e) in zip(stamps, ne)
    )
    (run / "pointcloud_locations_20m.csv").write_text(text)
    rng = np.random.default_rng(1)
    submap = rng.uniform(-1, 1, size=(4096, 3))
    submap.astype("<f8").tofile(run / "pointcloud_20m" / f"{stamps[0]}.bin")
    assert guess_poses_format(run / "pointcloud_locations_20m.csv") == "oxford"
    keys, T, _, _ = read_poses(run / "pointcloud_locations_20m.csv")
    np.testing.assert_allclose(keys, np.array(stamps) * 1e-6)
    np.testing.assert_allclose(T[:, :2, 3], ne)
    np.testing.assert_allclose(T[:, :3, :3], np.tile(np.eye(3), (2, 1, 1)))
    # The submap folder is found from the run, its format from the folder name.
    paths = list_scans(run)
    assert [p.name for p in paths] == [f"{stamps[0]}.bin"]
    pts = read_scan(paths[0])
    assert pts.shape == (4096, 4) and pts.dtype == np.float32
    # Metres at the default 20 m per unit, x negated back (PointNetVLAD negated all three).
    np.testing.assert_allclose(pts[:, :3], submap * [-20.0, 20.0, 20.0], atol=1e-4)
    assert np.all(pts[:, 3] == 0)
    from disco_cli.io.readers import oxford

    with oxford.scale(5.0):
        np.testing.assert_allclose(read_scan(paths[0])[:, :3], submap * [-5, 5, 5], atol=1e-5)
    np.testing.assert_allclose(read_scan(paths[0])[:, :3], pts[:, :3])  # the default again
    with pytest.raises(DiscoError, match="positive"), oxford.scale(0.0):
        pass
    # The frame: points in PointNetVLAD's vehicle frame (x forward, y right, z down),
    # centred, scaled and negated as generate_submaps.m does, come back x forward, y left,
    # z up: a wall 8 m ahead on the left, 4 m above the ground.
    ned = np.array([[8.0, -3.0, -4.0], [8.0, -3.0, 0.0], [-6.0, 5.0, -1.0]])
    c = ned.mean(axis=0)
    m = 20.0
    stored = -(ned - c) / m  # scale 1 / m: the reader's 20 m per unit gives metres back
    # (then the submap's points: a .bin is read as a scan from 1,000 points)
    np.vstack([stored, submap]).astype("<f8").tofile(run / "pointcloud_20m" / "frame.bin")
    back = read_scan(run / "pointcloud_20m" / "frame.bin")[:3, :3]
    np.testing.assert_allclose(back, (ned - c) * [1.0, -1.0, -1.0], atol=1e-5)
    assert back[0, 1] > 0 and back[0, 2] > back[1, 2]  # on the left; higher up
    # A file of another size is refused in one line.
    (run / "pointcloud_20m" / "bad.bin").write_bytes(b"\0" * 25)
    from disco_cli.errors import ScanReadError

    with pytest.raises(ScanReadError, match="24-byte"):
        read_scan(run / "pointcloud_20m" / "bad.bin", "oxford")


def test_kitti360_frames_and_velodyne_calibration(tmp_path):
    T, _ = known_poses()
    frames = np.array([3, 4, 5, 9, 10, 11])
    seq = tmp_path / "KITTI-360" / "data_poses" / "2013_05_28_drive_0000_sync"
    seq.mkdir(parents=True)
    rows = [f"{f} " + " ".join(f"{v:.17g}" for v in Ti[:3, :4].ravel()) for f, Ti in zip(frames, T)]
    (seq / "poses.txt").write_text("\n".join(rows) + "\n")
    assert guess_poses_format(seq / "poses.txt") == "kitti360"
    keys, imu, _, _ = read_poses(seq / "poses.txt", calib="none")
    np.testing.assert_allclose(keys, frames * 0.1)
    np.testing.assert_allclose(imu, T, atol=1e-12)
    # Calibration files in the dataset's calibration/ folder are found and used:
    # T_world<-velo = T_world<-imu @ T_imu<-cam0 @ inv(T_velo<-cam0).
    rng = np.random.default_rng(3)
    from scipy.spatial.transform import Rotation

    def rigid():
        M = np.eye(4)
        M[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        M[:3, 3] = rng.normal(size=3)
        return M

    cam_to_pose, cam_to_velo = rigid(), rigid()
    calib = tmp_path / "KITTI-360" / "calibration"
    calib.mkdir()
    fmt12 = lambda M: " ".join(f"{v:.17g}" for v in M[:3, :4].ravel())  # noqa: E731
    (calib / "calib_cam_to_pose.txt").write_text(
        f"image_00: {fmt12(cam_to_pose)}\nimage_01: {fmt12(rigid())}\n"
    )
    (calib / "calib_cam_to_velo.txt").write_text(fmt12(cam_to_velo) + "\n")
    _, velo, _, frame = read_poses(seq / "poses.txt")
    np.testing.assert_allclose(velo, T @ cam_to_pose @ np.linalg.inv(cam_to_velo), atol=1e-9)
    assert str(calib) in frame
    # Without the files, KITTI-360's published values: the Velodyne (x forward, y left,
    # z up) sits within a metre or two of the IMU/pose frame's origin, whose axes are
    # x forward, y right, z down: 180 degrees about x, to within a degree.
    (calib / "calib_cam_to_pose.txt").unlink()
    _, velo_pub, _, _ = read_poses(seq / "poses.txt")
    offset = np.linalg.inv(T[0]) @ velo_pub[0]
    assert 0.3 < np.linalg.norm(offset[:3, 3]) < 2.0
    turn = np.diag([1.0, -1.0, -1.0]).T @ offset[:3, :3]
    assert np.degrees(np.arccos((np.trace(turn) - 1) / 2)) < 1.0


def test_kitti_calib_and_extrinsic(tmp_path):
    from disco_cli.io.poses import write_kitti_poses

    T, _ = known_poses()
    write_kitti_poses(tmp_path / "poses.txt", T)
    Tr = np.eye(4)
    Tr[:3, :3] = rot_x(np.radians(-90)) @ rot_z(np.radians(-90))
    Tr[:3, 3] = [0.1, -0.08, -0.27]
    row = " ".join(f"{v:.17g}" for v in Tr[:3, :4].ravel())
    (tmp_path / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {row}\n")
    _, velo, fmt, _ = read_poses(tmp_path / "poses.txt")
    assert fmt == "kitti"
    np.testing.assert_allclose(velo, np.linalg.inv(Tr) @ T @ Tr, atol=1e-9)
    _, cam, _, _ = read_poses(tmp_path / "poses.txt", calib="none")
    np.testing.assert_allclose(cam, T, atol=1e-8)
    # --extrinsic: a 4 x 4 text right-multiplied after the calibration.
    E = np.eye(4)
    E[:3, :3] = rot_z(0.5)
    E[:3, 3] = [1.0, 2.0, 3.0]
    np.savetxt(tmp_path / "ext.txt", E)
    _, both, _, _ = read_poses(tmp_path / "poses.txt", extrinsic=tmp_path / "ext.txt")
    np.testing.assert_allclose(both, np.linalg.inv(Tr) @ T @ Tr @ E, atol=1e-8)


def test_bad_files_are_one_line_errors(tmp_path):
    (tmp_path / "odd.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(PoseFileError, match="cannot tell the pose format"):
        guess_poses_format(tmp_path / "odd.txt")
    (tmp_path / "traj.txt").write_text("0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n")
    with pytest.raises(PoseFileError, match="line 2: not a number"):
        read_poses(tmp_path / "traj.txt")
    with pytest.raises(PoseFileError, match="unknown pose format"):
        read_poses(tmp_path / "traj.txt", poses_format="vicon")
    (tmp_path / "traj.txt").write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    (tmp_path / "ext.txt").write_text("1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(PoseFileError, match="not a rigid transform"):
        read_poses(tmp_path / "traj.txt", poses_format="tum", extrinsic=tmp_path / "ext.txt")
    (tmp_path / "groundtruth_2012-01-08.csv").write_text("nan,nan,nan,nan,nan,nan,nan\n")
    with pytest.raises(PoseFileError, match="no poses"):
        read_poses(tmp_path / "groundtruth_2012-01-08.csv")
    with pytest.raises(PoseFileError, match="--extrinsic"):
        read_poses(tmp_path / "traj.txt", poses_format="tum", calib=tmp_path / "ext.txt")
