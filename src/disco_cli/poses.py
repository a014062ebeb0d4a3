"""KITTI poses, calibration and times; x, y, yaw helpers; ground-truth revisits.

A pose is the 4 x 4 transform of a sensor into the world frame (`T_world<-sensor`).
A KITTI `poses.txt` holds one 3 x 4 row-major pose per line. KITTI's own ground
truth is that of camera 0; with the sequence's `calib.txt` it becomes the LiDAR's:
`T_velo_i = inv(Tr) @ P_i @ Tr`.

Yaw convention (docs/architecture.md): the relative yaw of a query to a match is the
yaw of `T_match^-1 @ T_query`, i.e. the heading of the query sensor in the match's
frame, wrapped to (-180, 180] degrees.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError

__all__ = [
    "read_kitti_poses",
    "write_kitti_poses",
    "read_calib_tr",
    "read_times",
    "write_times",
    "xy_yaw",
    "wrap_deg",
    "relative_yaw_deg",
    "pair_distances",
    "gt_pairs",
    "gt_pairs_within",
    "nearest_distance",
]


def _read_lines(path: str | Path) -> list[str]:
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: no such file")
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise PoseFileError(f"{path}: cannot read ({exc})") from None


def _floats(path: str | Path, lineno: int, fields: list[str], want: int) -> np.ndarray:
    if len(fields) != want:
        raise PoseFileError(f"{path}, line {lineno}: expected {want} numbers, found {len(fields)}")
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        bad = " ".join(fields)
        raise PoseFileError(f"{path}, line {lineno}: not a number in {bad!r}") from None
    if not np.all(np.isfinite(values)):
        raise PoseFileError(f"{path}, line {lineno}: NaN or Inf")
    return values


def _to_4x4(values12: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = values12.reshape(3, 4)
    return T


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
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise PoseFileError(f"{path}: no poses")
    poses = np.empty((len(lines), 4, 4))
    for i, line in enumerate(lines):
        poses[i] = _to_4x4(_floats(path, i + 1, line.split(), 12))
    if calib is not None:
        Tr = read_calib_tr(calib) if isinstance(calib, (str, Path)) else np.asarray(calib, float)
        if Tr.shape != (4, 4):
            raise PoseFileError(f"calibration must be 4 x 4, got {Tr.shape}")
        poses = np.linalg.inv(Tr) @ poses @ Tr
    return poses


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
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise PoseFileError(f"{path}: no times")
    return np.array([_floats(path, i + 1, line.split(), 1)[0] for i, line in enumerate(lines)])


def write_times(path: str | Path, times: np.ndarray) -> None:
    Path(path).write_text("".join(f"{t + 0.0:.6f}\n" for t in np.asarray(times, float)))


def xy_yaw(T: np.ndarray) -> tuple:
    """(x, y, yaw in radians) of one 4 x 4 pose (floats) or of a stack (arrays)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"expected [..., 4, 4] poses, got {T.shape}")
    x, y = T[..., 0, 3], T[..., 1, 3]
    yaw = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    if T.ndim == 2:
        return float(x), float(y), float(yaw)
    return x, y, yaw


def wrap_deg(angle: np.ndarray | float) -> np.ndarray | float:
    """Angles in degrees wrapped to (-180, 180]."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = a - 360.0 * np.ceil((a - 180.0) / 360.0)
    return float(wrapped) if wrapped.ndim == 0 else wrapped


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (stack-aware), exact for rotations."""
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def relative_yaw_deg(T_match: np.ndarray, T_query: np.ndarray) -> np.ndarray | float:
    """Yaw of `T_match^-1 @ T_query` in degrees, wrapped to (-180, 180] (broadcasts)."""
    T_match = np.asarray(T_match, dtype=np.float64)
    T_query = np.asarray(T_query, dtype=np.float64)
    rel = _inv(T_match) @ T_query
    return wrap_deg(np.degrees(np.arctan2(rel[..., 1, 0], rel[..., 0, 0])))


def pair_distances(poses_a: np.ndarray, poses_b: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Euclidean distance (m) between the positions of each pair (i in a, j in b)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    d = poses_a[pairs[:, 0], :3, 3] - poses_b[pairs[:, 1], :3, 3]
    return np.linalg.norm(d, axis=1)


def gt_pairs(query_poses: np.ndarray, map_poses: np.ndarray, radius: float) -> np.ndarray:
    """All pairs `(i_query, j_map)` whose positions lie within `radius` metres (3D).

    Returns `[M, 2]` int64 sorted by query, then map index.
    """
    from scipy.spatial import cKDTree

    q = np.asarray(query_poses, float)[:, :3, 3]
    m = np.asarray(map_poses, float)[:, :3, 3]
    if len(q) == 0 or len(m) == 0:
        return np.zeros((0, 2), np.int64)
    hits = cKDTree(m).query_ball_point(q, r=radius)
    pairs = [(i, j) for i, js in enumerate(hits) for j in sorted(js)]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def gt_pairs_within(
    poses: np.ndarray,
    radius: float,
    exclude_frames: int = 50,
    times: np.ndarray | None = None,
    exclude_s: float | None = None,
) -> np.ndarray:
    """Revisits inside one sequence: pairs `(i, j)`, `i > j` (the later frame is the query).

    Frames closer than `exclude_frames` in index (and, with `times` and `exclude_s`,
    closer than `exclude_s` seconds) are not revisits but the same pass.
    """
    pairs = gt_pairs(poses, poses, radius)
    keep = pairs[:, 0] - pairs[:, 1] >= max(int(exclude_frames), 1)
    if times is not None and exclude_s is not None:
        t = np.asarray(times, float)
        keep &= t[pairs[:, 0]] - t[pairs[:, 1]] >= exclude_s
    return pairs[keep]


def nearest_distance(
    query_poses: np.ndarray, map_poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each query pose: (distance to the nearest map pose, its index)."""
    from scipy.spatial import cKDTree

    q = np.asarray(query_poses, float)[:, :3, 3]
    m = np.asarray(map_poses, float)[:, :3, 3]
    dist, idx = cKDTree(m).query(q)
    return dist, idx.astype(np.int64)
