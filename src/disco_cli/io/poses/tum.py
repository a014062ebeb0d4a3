"""TUM trajectories: one pose per line, `t tx ty tz qx qy qz qw`.

`t` is in seconds; the quaternion (Hamilton, x, y, z, w) and the translation give the
pose of the tracked frame in the world, `T_world<-frame`. Lines starting with `#` are
comments (the TUM RGB-D benchmark's files open with such a header). This is what
KISS-ICP, evo and disco's own `loops -o x.tum` write.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses._text import numeric_table
from disco_cli.io.poses.geometry import matrix_to_quat, quat_to_matrix


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N] seconds, poses [N, 4, 4]) of a TUM file, in file order."""
    table, _ = numeric_table(path, 8, "poses")
    with np.errstate(over="ignore", invalid="ignore"):  # an overflowing one is refused below
        norms = np.linalg.norm(table[:, 4:8], axis=1)
    bad = np.flatnonzero(~(norms > 1e-12) | ~np.isfinite(norms))
    if len(bad):
        raise PoseFileError(
            f"{path}: pose {bad[0] + 1} has a quaternion of zero (or overflowing) length"
        )
    T = np.tile(np.eye(4), (len(table), 1, 1))
    T[:, :3, :3] = quat_to_matrix(table[:, 4:8])
    T[:, :3, 3] = table[:, 1:4]
    return table[:, 0], T


def write_tum_poses(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write `[N, 4, 4]` poses at `stamps` (seconds) as TUM lines."""
    poses = np.asarray(poses, dtype=np.float64)
    q = matrix_to_quat(poses[:, :3, :3])
    lines = []
    for t, T, qi in zip(np.asarray(stamps, float), poses, q):
        values = [*T[:3, 3], *qi]
        lines.append(f"{t:.9f} " + " ".join(f"{v + 0.0:.9e}" for v in values) + "\n")
    Path(path).write_text("".join(lines))
