"""NCLT ground truth: `groundtruth_YYYY-MM-DD.csv` with `utime, x, y, z, roll, pitch, yaw`.

`utime` is in microseconds; x, y, z in metres and roll, pitch, yaw in radians give the
pose of the robot's body frame in NCLT's world frame, `R = Rz(yaw) Ry(pitch) Rx(roll)`.
Both frames follow NCLT's north-east-down convention (x forward, y right, z down for the
body). The files hold rows of NaN where the ground truth is unknown; they are skipped.
Scans are `velodyne_sync/<utime>.bin`, stamped in the same microseconds.

The Velodyne HDL-32E sits on the body at `X_BODY_VELO`: x, y, z (m), roll, pitch, yaw
(deg), the values NCLT publishes with its dataset tools and in Carlevaris-Bianco et
al., "University of Michigan North Campus long-term vision and lidar dataset", IJRR
2016 (the `x_body_velo` of its `project_vel_to_cam.py`).

NCLT's frames have z pointing down; disco's are z up. The `nclt` scan reader returns
points turned 180 degrees about x (`disco_cli.io.readers.nclt.TURN`), and the LiDAR poses
made here are those of that same turned frame, in the world turned the same way
(x north, y west, z up): `X @ P @ x_body_velo @ X` with `X = diag(1, -1, -1, 1)`
(`lidar_calibration`). Relative poses between scans therefore map returned points onto
returned points, and yaw is counter-clockwise seen from above.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from disco_cli.io.poses._text import numeric_table
from disco_cli.io.poses.geometry import xyzrpy_to_4x4
from disco_cli.io.readers.nclt import TURN

# NCLT: Velodyne in the body frame (x, y, z in m; roll, pitch, yaw in degrees).
X_BODY_VELO = (0.002, -0.004, -0.957, 0.807, 0.166, -90.703)

NAME = re.compile(r"groundtruth_\d{4}-\d{2}-\d{2}\.csv$")
UNIT_S = 1e-6  # scan names and utime are microseconds


def body_to_velo() -> np.ndarray:
    """`T_body<-velo`: the Velodyne's pose in NCLT's body frame (4 x 4)."""
    x, y, z, r, p, yaw = X_BODY_VELO
    return xyzrpy_to_4x4(x, y, z, np.radians(r), np.radians(p), np.radians(yaw))


def lidar_calibration() -> tuple[np.ndarray, np.ndarray]:
    """(left, right): the z-up LiDAR pose of a body pose P is `left @ P @ right`, in the
    frame the `nclt` scan reader returns (z up), in a z-up world."""
    X = np.diag([*TURN, 1.0])  # its own inverse
    return X, body_to_velo() @ X


def read_nclt_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N] seconds, body poses [N, 4, 4]); rows with NaN are skipped."""
    table, _ = numeric_table(path, 7, "poses", allow_nan=True)
    T = xyzrpy_to_4x4(table[:, 1], table[:, 2], table[:, 3], table[:, 4], table[:, 5], table[:, 6])
    return table[:, 0] * UNIT_S, T


def write_nclt_poses(path: str | Path, utimes: np.ndarray, poses: np.ndarray) -> None:
    """Write body poses as NCLT ground-truth rows (utime in microseconds, angles in radians)."""
    poses = np.asarray(poses, dtype=np.float64)
    R = poses[:, :3, :3]
    # Inverse of Rz(yaw) Ry(pitch) Rx(roll) away from pitch = +-90 deg.
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    pitch = np.arcsin(np.clip(-R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    rows = np.c_[poses[:, :3, 3], roll, pitch, yaw]
    text = "".join(
        f"{int(u)}," + ",".join(f"{v + 0.0:.12g}" for v in row) + "\n"
        for u, row in zip(utimes, rows)
    )
    Path(path).write_text(text)
