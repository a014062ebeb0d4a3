"""Ground-truth revisits: pairs of poses within a radius, across or inside sequences."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from disco_cli.io.poses.geometry import relative_yaw_deg


def pair_distances(poses_a: np.ndarray, poses_b: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Euclidean distance (m) between the positions of each pair (i in a, j in b)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    d = poses_a[pairs[:, 0], :3, 3] - poses_b[pairs[:, 1], :3, 3]
    return np.linalg.norm(d, axis=1)


def gt_pairs(query_poses: np.ndarray, map_poses: np.ndarray, radius: float) -> np.ndarray:
    """All pairs `(i_query, j_map)` whose positions lie within `radius` metres (3D).

    Returns `[M, 2]` int64 sorted by query, then map index.
    """
    # deferred: scipy.spatial costs ~0.3 s, and io.poses loads on the query path
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
    # deferred: scipy.spatial costs ~0.3 s, and io.poses loads on the query path
    from scipy.spatial import cKDTree

    q = np.asarray(query_poses, float)[:, :3, 3]
    m = np.asarray(map_poses, float)[:, :3, 3]
    dist, idx = cKDTree(m).query(q)
    return dist, idx.astype(np.int64)


def revisit_pairs(
    poses: list[np.ndarray], radius: float, exclude_frames: int = 50
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """The true revisits of sequences (`[N, 4, 4]` poses each): inside the only one
    (`gt_pairs_within`), or of every later sequence in every earlier one. Yields
    `(q, m, pairs [M, 2], distance_m [M], yaw_deg [M])` for each (query sequence,
    match sequence) with revisits; yaw is the query's heading in the match's frame."""
    if len(poses) == 1:
        jobs = [(0, 0, gt_pairs_within(poses[0], radius, exclude_frames))]
    else:
        jobs = [
            (q, m, gt_pairs(poses[q], poses[m], radius))
            for q in range(len(poses))
            for m in range(q)
        ]
    for q, m, pairs in jobs:
        if len(pairs):
            dist = pair_distances(poses[q], poses[m], pairs)
            yield q, m, pairs, dist, relative_yaw_deg(poses[m][pairs[:, 1]], poses[q][pairs[:, 0]])
