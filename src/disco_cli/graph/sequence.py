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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.graph.pose_graph import Correction, PoseGraph
from disco_cli.io.output_paths import atomic_path
from disco_cli.io.poses import ScanPoser, scan_times, write_kitti_poses
from disco_cli.io.poses.tum import write_tum_poses

__all__ = [
    "Odometry",
    "SequenceCorrection",
    "correct_sequence",
    "read_odometry",
    "write_trajectory",
]

# The formats written back as they were read; the others are written as TUM.
WRITABLE = ("kitti", "tum")


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
    """`correction` (`pose_graph.Correction`) and the `loops` (`Loop`s) it used."""

    correction: Correction
    loops: list[Any]


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
    **graph_options: Any,
) -> SequenceCorrection:
    """Find the loops along `paths` with `detector` (a `LoopDetector` with `pose=True`: each
    loop needs its T), then optimize the `PoseGraph` of `odometry` and those loops.
    `graph_options`: `PoseGraph`'s (kernel, kernel_width, noise). `extra_loops` join
    the graph's input as they are (a test's injected false loop, say)."""
    loops: list[Any] = []
    stream = detector.add_files(
        paths, times=times, scan_format=scan_format, threads=threads, on_progress=on_progress
    )
    for found in stream:
        loops += found
    graph = PoseGraph(odometry, **graph_options)
    graph.add_loops(loops + list(extra_loops or []))
    return SequenceCorrection(graph.optimize(), loops)
