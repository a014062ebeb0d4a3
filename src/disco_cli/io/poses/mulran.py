"""MulRan ground truth: `global_pose.csv`, one row `timestamp_ns, r11, r12, r13, tx, r21, ...`.

Each row is the time in nanoseconds and the row-major 3 x 4 pose of the vehicle's base
frame in MulRan's global (UTM-based) frame, `T_world<-base`. Scans are
`sensor_data/Ouster/<timestamp_ns>.bin` (KITTI layout: float32 x, y, z, intensity).

The Ouster OS1-64 sits on the base at `X_BASE_OUSTER`: x, y, z (m), roll, pitch, yaw
(deg), `R = Rz(yaw) Ry(pitch) Rx(roll)`: the base_link -> ouster transform that MulRan's
own file player (irapkaist/file_player_mulran) publishes, from Kim et al., "MulRan:
Multimodal Range Dataset for Urban Place Recognition", ICRA 2020. The sensor is turned
by about 180 degrees: it looks backwards.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.io.poses._text import numeric_table, to_4x4
from disco_cli.io.poses.geometry import xyzrpy_to_4x4

X_BASE_OUSTER = (1.7042, -0.021, 1.8047, 0.0001, 0.0003, 179.6654)

NAME = "global_pose.csv"
UNIT_S = 1e-9  # scan names and stamps are nanoseconds


def base_to_ouster() -> np.ndarray:
    """`T_base<-ouster`: the Ouster's pose in MulRan's base frame (4 x 4)."""
    x, y, z, r, p, yaw = X_BASE_OUSTER
    return xyzrpy_to_4x4(x, y, z, np.radians(r), np.radians(p), np.radians(yaw))


def read_mulran_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N] seconds, base poses [N, 4, 4]) of a `global_pose.csv`."""
    table, _ = numeric_table(path, 13, "poses")
    # Seconds as float64 keep ~0.3 microseconds at today's epoch: far below a scan period.
    return table[:, 0] * UNIT_S, to_4x4(table[:, 1:]).reshape(-1, 4, 4)


def write_mulran_poses(path: str | Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Write base poses as `global_pose.csv` rows (integer nanoseconds, 12 numbers)."""
    rows = np.asarray(poses, dtype=np.float64)[:, :3, :4].reshape(len(poses), 12)
    text = "".join(
        f"{int(t)}," + ",".join(f"{v + 0.0:.12g}" for v in row) + "\n"
        for t, row in zip(stamps_ns, rows)
    )
    Path(path).write_text(text)
