"""Scan inputs of the commands: folders, files, bags and stdin expanded into scan paths,
and the pose and time rows that come with them (files beside the scans, or given).

`collect_scans` gathers a build's scans with their poses and times; `query_paths` and
`QueryPoses` the scans of `disco query`, which may stream from stdin.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, PoseFileError, ScanReadError
from disco_cli.io.poses import ScanPoser, find_pose_file, pose_rows, read_times
from disco_cli.io.readers import is_bag, list_scans

__all__ = [
    "stdin_paths",
    "query_paths",
    "frame_rows",
    "scan_paths",
    "file_beside",
    "sequence_times",
    "window_times",
    "QueryPoses",
    "ScanList",
    "collect_scans",
]


def stdin_paths() -> Iterator[str]:
    """Scan paths from stdin, one per line, read lazily (blank lines skipped)."""
    for line in sys.stdin:
        line = line.strip()
        if line:
            yield line


def query_paths(
    inputs: list[str], scan_format: str | None = None, topic: str | None = None
) -> tuple[Iterator[str], list[str] | None]:
    """`disco query`'s scans: folders and bags expanded as for build-db, `-` read from
    stdin line by line as they come; and their list when it is known up front (None with
    stdin or a bag, whose scans go one by one, by the frame number or time in the name)."""

    def expand(a: str) -> list[str]:
        listed = a != "-" and (is_bag(a) or Path(a).is_dir())
        return [str(f) for f in list_scans(a, scan_format, topic)] if listed else [a]

    given = [f for a in inputs for f in expand(a)]
    paths = (p for s in given for p in (stdin_paths() if s == "-" else [s]))
    return paths, None if "-" in given or any(map(is_bag, inputs)) else given


def frame_rows(paths: list[str], n_rows: int, source: str) -> np.ndarray:
    """Which row of a per-frame file (poses, times) belongs to each scan.

    Row i for the i-th scan when the counts agree; otherwise the frame number in each
    scan's name (KITTI `000123.bin` is row 123). `PoseFileError` when neither fits.
    """
    if len(paths) == n_rows:
        return np.arange(n_rows)
    rows = []
    for p in paths:
        stem = Path(p).stem
        if not stem.isdigit() or int(stem) >= n_rows:
            raise PoseFileError(
                f"{source}: {n_rows} rows for {len(paths)} scans, and {p} has no frame "
                "number within it"
            )
        rows.append(int(stem))
    return np.asarray(rows, dtype=np.int64)


def scan_paths(
    inputs: list[Any], scan_format: str | None = None, topic: str | None = None
) -> list[Path]:
    """The scan files of every input (files, folders or bags), in order; `ScanReadError`
    when there are none."""
    paths: list[Path] = []
    for item in inputs:
        paths += list_scans(item, format=scan_format, topic=topic)
    if not paths:
        raise ScanReadError(", ".join(map(str, inputs)), "no scans found")
    return paths


def file_beside(inputs: list[Path], given: Path | None, name: str | None = None) -> Path | None:
    """`given`, else NAME (default: the pose file, `disco_cli.io.poses.find_pose_file`) beside
    the scans when a single folder was given."""
    if given is not None:
        return given
    if len(inputs) != 1 or not inputs[0].is_dir():
        return None
    if name is None:
        return find_pose_file(inputs[0])
    return inputs[0] / name if (inputs[0] / name).is_file() else None


def sequence_times(folder: Any, paths: list[str], times_file: Any = None) -> np.ndarray | None:
    """The time (s) of each scan of a sequence: from `times_file`, else the header stamps
    of scans in a bag, else `times.txt` in `folder`, by row or frame number
    (`frame_rows`); None when there is none of these."""
    # deferred: io.readers.bags stays off the query path, which imports this module
    from disco_cli.io.readers.bags import scan_stamps

    stamps = scan_stamps(paths) if times_file is None else None
    if stamps is not None and np.isfinite(stamps).all():
        return stamps
    folder = Path(folder)
    times_file = times_file or (folder / "times.txt" if folder.is_dir() else None)
    if times_file is None or not Path(times_file).is_file():
        return None
    t = read_times(times_file)
    return t[frame_rows(paths, len(t), str(times_file))]


def window_times(
    folder: Any, paths: list[str], times_file: Any, exclude_seconds: float | None, warn: Any
) -> np.ndarray | None:
    """`sequence_times` for a window of `exclude_seconds` (a `DiscoError` where there
    are none; `warn` hears of times that go backwards)."""
    stamps = sequence_times(folder, paths, times_file)
    if exclude_seconds is None:
        return stamps
    if stamps is None:
        raise DiscoError(f"{folder}: --exclude-seconds needs times.txt beside the scans or --times")
    if np.any(np.diff(stamps) < 0):
        warn(f"{folder}: timestamps are not increasing; frames are taken in file order")
    return stamps


class QueryPoses:
    """The pose rows (x, y, z, yaw; NaN when unknown) of query scans from a pose file
    (`disco_cli.io.poses.ScanPoser`): for scans known up front (`paths`) KITTI's "row i for
    scan i" applies when their count is the file's; scans streamed (stdin) go one by one,
    by frame number or time. `missing` counts the queries without a pose; `warn` hears of
    them (once when streamed)."""

    def __init__(self, poses_file: Any, pose_opts: dict, paths: list[str] | None, warn: Any):
        self.poser = ScanPoser(poses_file, **pose_opts)
        self.warn = warn
        self.missing = 0
        self.rows = None
        if paths is not None:
            T, report = self.poser.poses(list(paths))
            self.rows = pose_rows(T)
            if report.warning():
                warn(report.warning())

    def __call__(self, index: int, path: str) -> np.ndarray:
        if self.rows is not None:
            row = self.rows[index]
        else:
            T, report = self.poser.poses([path])
            row = pose_rows(T)[0]
            if report.missing and not self.missing:
                self.warn(report.warning())
        if not np.isfinite(row[:2]).all():
            self.missing += 1
        return row

    def exclusion(self, m: Any, radius: float) -> Callable[[int, str], np.ndarray]:
        """`Map.query_files`'s `exclude` for map `m`: the query's own scan, and the
        scans within `radius` m (x, y) of its pose."""
        return lambda i, p: m.near(self(i, p)[:2], radius, p)


@dataclass
class ScanList:
    """The scans of a build in input order, with pose rows and times (NaN = unknown)."""

    paths: list[str]
    poses: np.ndarray  # [N, 4] x, y, z, yaw
    times: np.ndarray  # [N]
    no_pose: int = 0  # scans a pose file was given for that got no pose


def collect_scans(
    inputs: list[str],
    poses_file: Path | None,
    times_file: Path | None,
    calib: str | None,
    scan_format: str | None = None,
    pose_opts: dict | None = None,
    warn: Any = None,
    topic: str | None = None,
    pose_topic: str | None = None,
) -> ScanList:
    """Expand folders, files and `-` (stdin) into one list of scans.

    A folder with a pose file (`disco_cli.io.poses.find_pose_file`) and `times.txt` beside
    its scans brings them along unless `--poses` / `--times` are given; those cover all
    scans. Poses come from `disco_cli.io.poses.ScanPoser`; scans left without one are
    named in one `warn` per pose file and counted in `ScanList.no_pose`.
    Scans in a bag are timed by their header stamps, and posed from the bag's
    `pose_topic` when given (by time, like a pose file).
    """
    # deferred: io.readers.bags stays off the query path, which imports this module
    from disco_cli.io.readers.bags import scan_stamps

    opts = dict(pose_opts or {})
    opts.setdefault("calib", "auto" if calib is None else calib)
    paths: list[str] = []
    poses: list[np.ndarray] = []
    times: list[np.ndarray] = []
    seen: set[str] = set()
    no_pose = 0
    used: list[Path] = []  # the pose and times files read

    def lidar_rows(group: list[str], pose_file: Path) -> np.ndarray:
        nonlocal no_pose
        used.append(Path(pose_file))
        T, report = ScanPoser(pose_file, **opts).poses(group)
        if report.warning():
            (warn or warnings.warn)(report.warning())
        no_pose += report.missing
        return pose_rows(T)

    for item in inputs:
        if item == "-":
            group = list(stdin_paths())
        else:
            group = [str(p) for p in list_scans(item, scan_format, topic)]
        group = [p for p in dict.fromkeys(group) if p not in seen]
        seen.update(group)
        n = len(group)
        p_rows, t_rows = np.full((n, 4), np.nan), scan_stamps(group)
        folder = Path(item)
        if item != "-" and folder.is_dir() and group:
            beside = find_pose_file(folder) if poses_file is None else None
            if beside is not None:
                p_rows = lidar_rows(group, beside)
            if times_file is None and (folder / "times.txt").is_file():
                used.append(folder / "times.txt")
                t = read_times(folder / "times.txt")
                t_rows = t[frame_rows(group, len(t), str(folder / "times.txt"))]
        paths += group
        poses.append(p_rows)
        times.append(t_rows)
    all_poses = np.concatenate(poses) if poses else np.empty((0, 4))
    all_times = np.concatenate(times) if times else np.empty(0)
    if poses_file is not None:
        all_poses = lidar_rows(paths, poses_file)
    if times_file is not None:
        t = read_times(times_file)
        all_times = t[frame_rows(paths, len(t), str(times_file))]
    if pose_topic is not None:
        from disco_cli.io.readers.bags import bag_poses  # deferred: as scan_stamps above

        T, missing = bag_poses(paths, pose_topic, opts.get("max_time_gap"), opts.get("extrinsic"))
        if missing:
            (warn or warnings.warn)(
                f"{pose_topic}: {len(missing)} of {len(paths)} scans have no pose near their "
                f"stamp (e.g. {missing[0]}); they are left without one"
            )
        no_pose += len(missing)
        all_poses = pose_rows(T)
    from disco_cli.io.missed_poses import missed_hint  # deferred: it loads io.readers.bags

    # Poses or times left unused (a folder's poses.txt beside scans given one by one, a
    # bag's odometry topic): one line that says how to supply them.
    hint = missed_hint(
        paths,
        all_poses if poses_file is None and pose_topic is None else None,
        all_times if times_file is None else None,
        used=used,
    )
    if hint:
        (warn or warnings.warn)(hint)
    return ScanList(paths, all_poses, all_times, no_pose)
