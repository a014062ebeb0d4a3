"""KITTI-360 poses: `data_poses/<sequence>/poses.txt`, `frame r11 r12 r13 tx r21 ...`.

Each line is a frame index (of the 10 Hz sensor frames) and the row-major 3 x 4 pose of
the IMU/GPS ("pose") frame in the world, `T_world<-imu`. Only frames where the vehicle
moved have a line; frames in between get interpolated poses. Scans are
`data_3d_raw/<sequence>/velodyne_points/data/<frame:010d>.bin` (KITTI layout).

The LiDAR's pose is `T_world<-imu @ T_imu<-cam0 @ inv(T_velo<-cam0)` with the two
calibration files of the dataset's `calibration/` folder: `calib_cam_to_pose.txt`
(line `image_00:`, camera 0 -> pose frame) and `calib_cam_to_velo.txt` (camera 0 ->
Velodyne). When those files are not found, the values KITTI-360 publishes in them
(Liao et al., "KITTI-360", TPAMI 2022; the files as distributed) are used.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses._text import floats, numeric_table, read_lines, to_4x4
from disco_cli.io.poses.kitti import invert_calibration

# calibration/calib_cam_to_pose.txt, image_00 (camera 0 -> IMU/GPS pose frame).
CAM0_TO_POSE = (
    0.0371783278, -0.0986182135, 0.9944306009, 1.5752681039,
    0.9992675562, -0.0053553387, -0.0378902567, 0.0043914093,
    0.0090621821, 0.9951109327, 0.0983468786, -0.6500000000,
)  # fmt: skip
# calibration/calib_cam_to_velo.txt (camera 0 -> Velodyne).
CAM0_TO_VELO = (
    0.04307104361, -0.08829286498, 0.995162929, 0.8043914418,
    -0.999004371, 0.007784614041, 0.04392796942, 0.2993489574,
    -0.01162548558, -0.9960641394, -0.08786966659, -0.1770225824,
)  # fmt: skip

FRAME_S = 0.1  # the Velodyne's 10 Hz: frame index -> seconds


def read_kitti360_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(frame indices [N] as int64, IMU poses [N, 4, 4])."""
    table, _ = numeric_table(path, 13, "poses")
    frames = table[:, 0]
    # Frame numbers are integers from 0; past 2^53 a float64 holds no exact integer.
    if np.any(frames != np.round(frames)) or np.any(frames < 0) or np.any(frames > 2**53):
        raise PoseFileError(f"{path}: the first column must be frame numbers")
    return frames.astype(np.int64), to_4x4(table[:, 1:]).reshape(-1, 4, 4)


def find_calibration(poses_file: str | Path) -> Path | None:
    """The dataset's `calibration/` folder, searched upwards from a poses.txt."""
    for parent in Path(poses_file).resolve().parents:
        folder = parent / "calibration"
        if (folder / "calib_cam_to_pose.txt").is_file() and (
            folder / "calib_cam_to_velo.txt"
        ).is_file():
            return folder
    return None


def imu_to_velo(calibration: str | Path | None = None) -> np.ndarray:
    """`T_imu<-velo` (the Velodyne's pose in the IMU/pose frame) from a `calibration/`
    folder, or from the published values when `calibration` is None."""
    if calibration is None:
        cam_to_pose = to_4x4(np.array(CAM0_TO_POSE))
        cam_to_velo = to_4x4(np.array(CAM0_TO_VELO))
    else:
        folder = Path(calibration)
        cam_to_pose = None
        pose_file = folder / "calib_cam_to_pose.txt"
        for i, line in enumerate(read_lines(pose_file), start=1):
            key, _, rest = line.partition(":")
            if key.strip() == "image_00":
                cam_to_pose = to_4x4(floats(pose_file, i, rest.split(), 12))
        if cam_to_pose is None:
            raise PoseFileError(f"{pose_file}: no 'image_00:' line")
        velo_file = folder / "calib_cam_to_velo.txt"
        lines = [ln for ln in read_lines(velo_file) if ln.strip()]
        if not lines:
            raise PoseFileError(f"{velo_file}: empty")
        cam_to_velo = to_4x4(floats(velo_file, 1, lines[0].split(), 12))
        inverse = invert_calibration(cam_to_velo, velo_file)
        with np.errstate(over="ignore", invalid="ignore"):  # refused below, not warned of
            out = cam_to_pose @ inverse
        if not np.isfinite(out).all():
            raise PoseFileError(f"{folder}: calibration values overflow (far too large)")
        return out
    return cam_to_pose @ np.linalg.inv(cam_to_velo)
