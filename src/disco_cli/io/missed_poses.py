"""Poses and times the input could have given but did not: said, never dropped silently.

Scans listed one by one (or on stdin) from a folder with poses.txt, or a sequence's
velodyne/ folder given instead of the sequence, or a ROS bag with an odometry topic
read without --pose-topic: each ends up without a pose that was there to be had. These
functions find the source that was left unused and say how to supply it, in one line.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses import find_pose_file
from disco_cli.io.readers.bags import pose_topics, split_name


def _sequence_folders(scan: str) -> list[Path]:
    """Where a scan's pose or times file would lie: its folder, and the sequence folder
    above a KITTI-style velodyne/."""
    folder = Path(scan).parent
    return [folder, folder.parent] if folder.name == "velodyne" else [folder]


def _pose_file_near(scan: str) -> Path | None:
    for folder in _sequence_folders(scan):
        try:
            found = find_pose_file(folder)
        except PoseFileError:
            continue  # several candidates: not one to suggest
        if found is not None:
            return found
    return None


def _times_file_near(scan: str) -> Path | None:
    for folder in _sequence_folders(scan):
        if (folder / "times.txt").is_file():
            return folder / "times.txt"
    return None


def bag_pose_topics(bags: Iterable[str]) -> list[str]:
    """`/odom (nav_msgs/Odometry)` for each pose topic of these bags (unreadable bags:
    none; they fail with their own message where they are read)."""
    found: dict[str, str] = {}
    for bag in dict.fromkeys(bags):
        try:
            found.update(pose_topics(bag))
        except Exception:  # noqa: BLE001 - a hint must never be the failure
            continue
    return [f"{t} ({kind})" for t, kind in sorted(found.items())]


def bag_hint(paths: Sequence[object]) -> str:
    """`"; the bag has /odom (nav_msgs/Odometry): pass --pose-topic /odom"` when the
    scans come from bags with a pose topic, else ""."""
    topics = bag_pose_topics(b for b in (_bag_of(str(p)) for p in paths) if b is not None)
    if not topics:
        return ""
    return f"; the bag has {', '.join(topics)}: pass --pose-topic {topics[0].split(' ')[0]}"


def no_poses_error(paths: Sequence[object], what: str, flag: str) -> Exception:
    """The error of an evaluation given no poses: which option, or which bag topic."""
    return PoseFileError(
        f"no {what}: give {flag} FILE (or a folder with poses.txt){bag_hint(paths)}"
    )


def _bag_of(scan: str) -> str | None:
    parts = split_name(scan)
    return None if parts is None else parts[0]


def missed_hint(
    paths: Sequence[str],
    poses: np.ndarray | None,
    times: np.ndarray | None = None,
    *,
    used: Iterable[Path] = (),
) -> str | None:
    """One line when scans are left without a pose (rows of `poses`: NaN in column 0)
    or a time that a file beside them or their bag's pose topic would give; None when
    every scan has one or nothing could have given it. `poses` / `times` None: not
    checked (the user gave them). `used`: the pose and times files already read (their
    misses were named where they were read)."""
    used_files = {Path(p).resolve() for p in used}
    no_pose = [] if poses is None else np.flatnonzero(~np.isfinite(poses[:, 0])).tolist()
    hints: list[str] = []
    missed = 0
    files: dict[Path, int] = {}
    bag_scans: list[str] = []
    for i in no_pose:
        scan = str(paths[i])
        if _bag_of(scan) is not None:
            bag_scans.append(scan)
            continue
        near = _pose_file_near(scan)
        if near is not None and near.resolve() not in used_files:
            files[near] = files.get(near, 0) + 1
    hint = bag_hint(bag_scans)
    if hint:
        missed += len(bag_scans)
        hints.append(hint.removeprefix("; "))
    if files:
        missed += sum(files.values())
        first = next(iter(files))
        more = f" (and {len(files) - 1} more pose files)" if len(files) > 1 else ""
        hints.append(f"{first} is beside them{more}: pass --poses {first}, or give the folder")
    line = f"{missed} of {len(paths)} scans have no pose; {'; '.join(hints)}" if hints else ""
    if times is not None:
        t_files: dict[Path, int] = {}
        for i in range(len(paths)):
            if np.isfinite(times[i]) or _bag_of(str(paths[i])) is not None:
                continue
            near = _times_file_near(str(paths[i]))
            if near is not None and near.resolve() not in used_files:
                t_files[near] = t_files.get(near, 0) + 1
        if t_files:
            first = next(iter(t_files))
            n = sum(t_files.values())
            t_line = (
                f"{n} of {len(paths)} scans have no time; {first} is beside them: "
                f"pass --times {first}"
            )
            line = f"{line}; {t_line}" if line else t_line
    return line or None
