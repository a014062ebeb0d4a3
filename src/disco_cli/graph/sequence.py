"""`disco correct` as library calls: a sequence's odometry in, loops found along it,
the pose graph optimized, the corrected trajectory out in the odometry's own format.

    odo = read_odometry(paths, "odom.tum", times=stamps)          # one pose per scan
    detector = LoopDetector("default", pose=True)
    result = correct_sequence(paths, odo.poses, detector, times=stamps)
    write_trajectory("corrected.tum", odo, result.correction.poses)

The odometry is the LiDAR's pose in its world (`T_world<-lidar`, what KISS-ICP writes):
it is read as stored, with no calibration, so that the corrected file is the same
kind of file. Each scan takes its odometry pose by frame (KITTI: row i for scan i, or
the row of the scan's frame number) or by time (TUM and the time-stamped formats,
interpolated), as `poses_for_scans` gives poses to every command.

The loops are found as `disco loops` finds them (its detector, its confidence bar, no
pose), and only then does each loop that goes into the graph get its relative pose
(ICP, tens of milliseconds a loop): one loop for every `LOOP_EVERY` scans of a revisit,
as consecutive scans' loops say nearly the same thing. On the selection worlds a third
of the loops gave the graph the ATE of all of them (within 0.01 of the ratio on
eight of nine worlds, 0.99-1.12x the true loops' either way; docs/correct.md), at a
third of the ICP time.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, PoseFileError
from disco_cli.graph.pose_graph import Correction, correct
from disco_cli.io.output_paths import atomic_path
from disco_cli.io.poses import ScanPoser, scan_times, write_kitti_poses
from disco_cli.io.poses.tum import write_tum_poses
from disco_cli.io.readers import read_scan
from disco_cli.query.localize import pose_fields
from disco_cli.query.relative_pose import estimate_relative_pose
from disco_cli.runtime.threads import get_threads

__all__ = [
    "Odometry",
    "SequenceCorrection",
    "correct_sequence",
    "pose_loops",
    "thin_loops",
    "read_odometry",
    "write_trajectory",
]

# The formats written back as they were read; the others are written as TUM.
WRITABLE = ("kitti", "tum")
# One loop into the graph for every this many scans of a revisit (see the module).
LOOP_EVERY = 3


@dataclass(frozen=True)
class Odometry:
    """One odometry pose per scan: `poses` `[N, 4, 4]`, the file's `format`, the scans'
    `stamps` (seconds; NaN where unknown) and `source` (the file)."""

    poses: np.ndarray = field(repr=False)
    format: str
    stamps: np.ndarray = field(repr=False)
    source: str

    @property
    def out_format(self) -> str:
        """The format the corrected trajectory is written in."""
        return self.format if self.format in WRITABLE else "tum"


def read_odometry(
    paths: list[str],
    odometry_file: str | Path,
    poses_format: str | None = None,
    times: np.ndarray | None = None,
) -> Odometry:
    """The odometry pose of every scan in `paths`; `PoseFileError` naming the file when a
    scan has none (a pose graph needs every pose). `times`: the scans' seconds (a
    `times.txt`), else they come from the scan names where the format is by time."""
    poser = ScanPoser(odometry_file, poses_format, calib="none")
    poses, report = poser.poses(paths, times)
    if report.missing:
        examples = ", ".join(report.examples)
        raise PoseFileError(
            f"{odometry_file}: {report.missing} of {report.scans} scans have no odometry pose "
            f"(e.g. {examples}); disco correct needs one for every scan"
        )
    if times is not None:
        stamps = np.asarray(times, dtype=np.float64)
    elif poser.format == "kitti":
        stamps = np.arange(len(paths), dtype=np.float64)
    else:
        stamps = scan_times(paths, poser.format)
    return Odometry(poses, poser.format, stamps, str(odometry_file))


def write_trajectory(path: str | Path, odometry: Odometry, poses: np.ndarray) -> str:
    """Write `poses` (one per scan) in the odometry's format (TUM for formats disco does
    not write), atomically; returns the format written."""
    fmt = odometry.out_format
    with atomic_path(path) as tmp:
        if fmt == "kitti":
            write_kitti_poses(tmp, poses)
        else:
            write_tum_poses(tmp, odometry.stamps, poses)
    return fmt


@dataclass(frozen=True)
class SequenceCorrection:
    """`correction` (`pose_graph.Correction`), the `loops` (`Loop`s, each with its
    pose) it used, and how many loops the detector `found` (before `thin_loops`)."""

    correction: Correction
    loops: list[Any]
    found: int = 0


def thin_loops(loops: list[Any], every: int = LOOP_EVERY) -> list[Any]:
    """The loops in query order, each kept only `every` or more scans after the last
    one kept (`every` 1: all of them)."""
    kept: list[Any] = []
    for lp in sorted(loops, key=lambda lp: lp.query_index):
        if not kept or lp.query_index - kept[-1].query_index >= every:
            kept.append(lp)
    return kept


def pose_loops(
    paths: list[str],
    loops: list[Any],
    *,
    scan_format: str | None = None,
    config: Any = None,
    threads: int | None = None,
) -> tuple[list[Any], list[str]]:
    """Each loop without a pose given its relative pose (`estimate_relative_pose` from
    the loop's yaw, the two scans read from `paths`), on `threads` threads (None:
    `get_threads()`). Returns the loops with a pose, and why each of the others has
    none."""

    def posed(lp: Any) -> Any:
        if getattr(lp, "T", None) is not None:
            return lp
        try:
            query = read_scan(paths[lp.query_index], scan_format)
            match = read_scan(paths[lp.match_index], scan_format)
            rp = estimate_relative_pose(query, match, lp.yaw_deg, config)
        except DiscoError as exc:  # one unusable pair must not cost the others
            return f"scan {lp.query_index} -> {lp.match_index}: no relative pose ({exc})"
        return replace(lp, **pose_fields(rp))

    workers = max(1, min(threads or get_threads(), len(loops)))
    if workers == 1:
        results = [posed(lp) for lp in loops]
    else:  # the ICP releases the GIL
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(posed, loops))
    return [r for r in results if not isinstance(r, str)], [
        r for r in results if isinstance(r, str)
    ]


def correct_sequence(
    paths: list[str],
    odometry: np.ndarray,
    detector: Any,
    *,
    times: np.ndarray | None = None,
    scan_format: str | None = None,
    threads: int | None = None,
    on_progress: Callable[[int], None] | None = None,
    extra_loops: list[Any] | None = None,
    loop_every: int = LOOP_EVERY,
    on_pose_error: Callable[[str], None] | None = None,
    **graph_options: Any,
) -> SequenceCorrection:
    """Find the loops along `paths` with `detector` (a `LoopDetector`; `disco loops`'
    defaults need no pose), keep one for every `loop_every` scans (`thin_loops`), give
    those without a pose theirs (`pose_loops`), then optimize the `PoseGraph` of
    `odometry` and those loops. `graph_options`: `PoseGraph`'s (kernel, kernel_width,
    noise, drift). `extra_loops` join the graph's input as they are (a test's injected
    false loop, say). `on_pose_error(message)` hears of a loop left out for want of a
    pose."""
    found: list[Any] = []
    stream = detector.add_files(
        paths, times=times, scan_format=scan_format, threads=threads, on_progress=on_progress
    )
    for loops in stream:
        found += loops
    config = getattr(detector, "pose_config", None)
    loops, errors = pose_loops(
        paths, thin_loops(found, loop_every), scan_format=scan_format, config=config,
        threads=threads,
    )  # fmt: skip
    for message in errors:
        if on_pose_error is not None:
            on_pose_error(message)
    correction = correct(odometry, loops + list(extra_loops or []), **graph_options)
    return SequenceCorrection(correction, loops, len(found))
