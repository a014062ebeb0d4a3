"""KITTI odometry poses, calibration and times.

A KITTI `poses.txt` holds one 3 x 4 row-major pose per line, line i for frame i. KITTI's
own ground truth is that of camera 0 in camera 0's frame at frame 0; with the
sequence's `calib.txt` (`Tr`: LiDAR -> camera 0) it becomes the LiDAR's, in the LiDAR's
frame at frame 0: `T_velo_i = inv(Tr) @ P_i @ Tr`. A `times.txt` holds one time
(seconds) per frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses._text import floats as _floats
from disco_cli.io.poses._text import read_lines as _read_lines
from disco_cli.io.poses._text import to_4x4 as _to_4x4


def read_calib_tr(path: str | Path) -> np.ndarray:
    """The `Tr:` line of a KITTI `calib.txt` (LiDAR -> camera 0) as a 4 x 4 matrix."""
    for lineno, line in enumerate(_read_lines(path), start=1):
        key, _, rest = line.partition(":")
        if key.strip() == "Tr":
            return _to_4x4(_floats(path, lineno, rest.split(), 12))
    raise PoseFileError(f"{path}: no 'Tr:' line")


def read_kitti_poses(path: str | Path, calib: str | Path | np.ndarray | None = None) -> np.ndarray:
    """Poses of a KITTI `poses.txt` as `[N, 4, 4]` float64.

    `calib` (a `calib.txt` path or the 4 x 4 `Tr` itself) turns camera-0 poses into
    LiDAR poses. Blank lines are allowed only at the end of the file.
    """
    lines = _read_lines(path)
    if not lines:
        raise PoseFileError(f"{path}: no poses")
    poses = np.empty((len(lines), 4, 4))
    for i, line in enumerate(lines):
        poses[i] = _to_4x4(_floats(path, i + 1, line.split(), 12))
    if calib is not None:
        Tr = read_calib_tr(calib) if isinstance(calib, (str, Path)) else np.asarray(calib, float)
        if Tr.shape != (4, 4):
            raise PoseFileError(f"calibration must be 4 x 4, got {Tr.shape}")
        poses = invert_calibration(Tr, calib) @ poses @ Tr
    return poses


def invert_calibration(Tr: np.ndarray, source: object) -> np.ndarray:
    """inv(Tr), or `PoseFileError` naming `source` when Tr has no finite inverse."""
    where = source if isinstance(source, (str, Path)) else "the calibration"
    try:
        inv = np.linalg.inv(Tr)
    except np.linalg.LinAlgError:
        raise PoseFileError(f"{where}: Tr is not invertible") from None
    if not np.isfinite(inv).all():
        raise PoseFileError(f"{where}: Tr is not invertible")
    return inv


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    """Write `[N, 4, 4]` (or `[N, 3, 4]`) poses as KITTI lines (fixed format, reproducible)."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be [N, 4, 4] or [N, 3, 4], got {poses.shape}")
    rows = poses[:, :3, :4].reshape(len(poses), 12)
    # +0.0 turns -0.0 into 0.0 so that equal poses always print the same.
    text = "".join(" ".join(f"{v + 0.0:.9e}" for v in row) + "\n" for row in rows)
    Path(path).write_text(text)


def read_times(path: str | Path) -> np.ndarray:
    """Timestamps (seconds, one per line) as `[N]` float64."""
    lines = _read_lines(path)
    if not lines:
        raise PoseFileError(f"{path}: no times")
    return np.array([_floats(path, i + 1, line.split(), 1)[0] for i, line in enumerate(lines)])


def write_times(path: str | Path, times: np.ndarray) -> None:
    Path(path).write_text("".join(f"{t + 0.0:.6f}\n" for t in np.asarray(times, float)))
