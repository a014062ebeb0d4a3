"""Poses for scans: one function, `poses_for_scans`, that every command uses.

Each pose file format is read by its own module; here a format is chosen (or guessed),
its poses are brought to the LiDAR frame (the calibration the dataset publishes, and an
optional user extrinsic), and each scan gets its pose:

- by frame number (kitti): row i for the i-th scan when the file has exactly one row
  per scan, otherwise the row numbered like the scan's file name (`000123.bin` is row
  123): a pose file of a whole sequence serves any subset of its scans;
- by time (tum, nclt, mulran, oxford, kitti360): the scan's time (from its file name,
  or given) is matched exactly or interpolated between the two nearest poses
  (`interpolate.interpolate_poses`); a scan with no pose within `max_time_gap` is left
  without one (NaN) and counted in the report.

Frames: every returned pose is `T_world<-lidar`, with
`T_world<-lidar = T_world<-frame @ T_frame<-lidar @ extrinsic`, where `T_frame<-lidar`
is the format's calibration (see `FORMATS` and docs/formats.md, "Pose files") and
`extrinsic` the user's `--extrinsic` (identity when not given).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses._text import has_header, read_lines, split_fields
from disco_cli.io.poses.interpolate import EXACT_S, default_max_gap, interpolate_poses
from disco_cli.io.poses.kitti import invert_calibration, read_calib_tr, read_kitti_poses

__all__ = [
    "POSE_FORMATS",
    "PoseReport",
    "ScanPoser",
    "calib_arg",
    "find_pose_file",
    "guess_poses_format",
    "poses_for_scans",
    "read_extrinsic",
    "read_poses",
    "scan_times",
]

POSE_FORMATS = ("kitti", "tum", "nclt", "mulran", "oxford", "kitti360")
# Seconds per unit of the integer scan names of each time-stamped format.
_NAME_UNIT_S = {"nclt": 1e-6, "mulran": 1e-9, "oxford": 1e-6}


@dataclass(frozen=True)
class PoseReport:
    """How the scans got their poses.

    `missing`: scans left without a pose; `examples`: up to three of their names;
    `max_time_gap`: the largest gap used (s; None for frame-numbered KITTI poses);
    `frame`: a short description of the frame conversion applied.
    """

    source: str
    format: str
    scans: int
    with_pose: int
    exact: int
    interpolated: int
    missing: int
    examples: tuple[str, ...]
    max_time_gap: float | None
    frame: str

    def warning(self) -> str | None:
        """One line for stderr when some scans got no pose, else None."""
        if not self.missing:
            return None
        names = ", ".join(self.examples)
        more = f" (e.g. {names})" if names else ""
        gap = f" within {self.max_time_gap:.3g} s" if self.max_time_gap is not None else ""
        return (
            f"{self.source}: {self.missing} of {self.scans} scans have no pose{gap}{more}; "
            "they are left without one"
        )


def guess_poses_format(path: str | Path) -> str:
    """The format of a pose file from its name, else from its first data line.

    Names: `groundtruth_YYYY-MM-DD.csv` (nclt), `global_pose.csv` (mulran),
    `pointcloud_locations*.csv` (oxford), `poses.txt` (kitti, or kitti360 when its lines
    start with a frame number and hold 13 fields). Otherwise the fields per line:
    12 kitti, 13 with an integer first field kitti360 (a `.csv` of 13 is mulran), 8 tum,
    7 nclt. `PoseFileError` when none fits.
    """
    # deferred: each format's module loads when its poses are read, off the query path
    from disco_cli.io.poses import nclt, oxford

    path = Path(path)
    name = path.name.lower()
    if nclt.NAME.match(name):
        return "nclt"
    if name == "global_pose.csv":
        return "mulran"
    if name.startswith(oxford.NAME_PREFIX):
        return "oxford"
    lines = [ln for ln in read_lines(path) if ln.strip() and not ln.lstrip().startswith("#")]
    if lines and has_header(lines[0]):
        lines = lines[1:]
    if not lines:
        raise PoseFileError(f"{path}: no poses")
    fields = split_fields(lines[0])
    n = len(fields)
    if name == "poses.txt" and not (n == 13 and re.fullmatch(r"\d+", fields[0])):
        return "kitti"  # KITTI's name: its reader says what is wrong with a line
    if n == 12:
        return "kitti"
    if n == 13:
        if path.suffix.lower() == ".csv":
            return "mulran"
        if re.fullmatch(r"\d+", fields[0]):
            return "kitti360"
    if n == 8:
        return "tum"
    if n == 7:
        return "nclt"
    raise PoseFileError(
        f"{path}: cannot tell the pose format from {n} fields per line; "
        f"pass --poses-format ({'|'.join(POSE_FORMATS)})"
    )


def read_extrinsic(path: str | Path) -> np.ndarray:
    """A 4 x 4 rigid transform from a text file (16 numbers, or 12 for the top 3 x 4)."""
    fields = [f for ln in read_lines(path) if not ln.lstrip().startswith("#")
              for f in split_fields(ln)]  # fmt: skip
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise PoseFileError(f"{path}: not a 4 x 4 matrix of numbers") from None
    if len(values) not in (12, 16) or not np.all(np.isfinite(values)):
        raise PoseFileError(f"{path}: expected 16 (or 12) numbers, found {len(values)}")
    T = np.eye(4)
    T[: len(values) // 4] = values.reshape(-1, 4)
    R = T[:3, :3]
    # A rotation's entries lie within +-1: test that first, so R @ R.T cannot overflow.
    rigid = np.abs(R).max() <= 1.0 + 1e-4 and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
    if not np.allclose(T[3], [0, 0, 0, 1]) or not rigid:
        raise PoseFileError(f"{path}: not a rigid transform (rotation not orthonormal)")
    return T


def _calibration(
    fmt: str, poses_file: Path, calib: str | Path | np.ndarray | None
) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(left, right, description): LiDAR poses are `left @ P @ right` (None: identity)."""
    none = calib is None or (isinstance(calib, str) and calib.lower() == "none")
    auto = isinstance(calib, str) and calib.lower() == "auto"
    given = not none and not auto
    if fmt == "kitti":
        if none:
            return None, None, "as stored"
        if auto:
            beside = poses_file.parent / "calib.txt"
            if not beside.is_file():
                return None, None, "as stored (no calib.txt beside it)"
            calib = beside
        Tr = read_calib_tr(calib) if isinstance(calib, (str, Path)) else np.asarray(calib, float)
        if Tr.shape != (4, 4):
            raise PoseFileError(f"calibration must be 4 x 4, got {Tr.shape}")
        where = f" ({calib})" if isinstance(calib, (str, Path)) else ""
        return invert_calibration(Tr, calib), Tr, f"camera 0 -> LiDAR by calib.txt{where}"
    if fmt == "kitti360":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses import kitti360

        if none:
            return None, None, "IMU poses as stored"
        if isinstance(calib, np.ndarray):
            return None, np.asarray(calib, float), "IMU -> LiDAR by the given matrix"
        folder = kitti360.find_calibration(poses_file) if auto else Path(calib)
        if folder is not None and Path(folder).is_file():
            folder = Path(folder).parent
        right = kitti360.imu_to_velo(folder)
        src = str(folder) if folder is not None else "KITTI-360's published calibration"
        return None, right, f"IMU -> LiDAR by {src}"
    if given:
        raise PoseFileError(
            f"--calib applies to kitti and kitti360 poses; for {fmt} poses give the "
            "LiDAR's pose in their frame with --extrinsic FILE"
        )
    if none:
        return None, None, "as stored"
    if fmt == "nclt":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.nclt import lidar_calibration

        left, right = lidar_calibration()
        return left, right, "body -> Velodyne by NCLT's x_body_velo, turned z up"
    if fmt == "mulran":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.mulran import base_to_ouster

        return None, base_to_ouster(), "base -> Ouster by MulRan's calibration"
    return None, None, "as stored"


def _read_raw(
    path: str | Path,
    poses_format: str | None,
    calib: str | Path | np.ndarray | None,
    extrinsic: np.ndarray | str | Path | None,
) -> tuple[np.ndarray, np.ndarray, str, np.ndarray | None, np.ndarray | None, str]:
    """(keys, poses as stored, format, left, right, frame): LiDAR poses are
    `left @ P @ right`, where `right` includes the extrinsic (None: identity)."""
    path = Path(path)
    fmt = (poses_format or guess_poses_format(path)).lower()
    if fmt not in POSE_FORMATS:
        raise PoseFileError(f"unknown pose format {fmt!r} (known: {', '.join(POSE_FORMATS)})")
    if fmt == "kitti":
        T = read_kitti_poses(path)
        keys = np.arange(len(T), dtype=np.float64)
    elif fmt == "tum":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.tum import read_tum_poses

        keys, T = read_tum_poses(path)
    elif fmt == "nclt":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.nclt import read_nclt_poses

        keys, T = read_nclt_poses(path)
    elif fmt == "mulran":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.mulran import read_mulran_poses

        keys, T = read_mulran_poses(path)
    elif fmt == "oxford":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.oxford import read_oxford_locations

        keys, T = read_oxford_locations(path)
    else:
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.kitti360 import FRAME_S, read_kitti360_poses

        frames, T = read_kitti360_poses(path)
        keys = frames * FRAME_S
    if not (np.isfinite(keys).all() and np.isfinite(T).all()):
        raise PoseFileError(f"{path}: poses or times overflow to Inf or NaN (values far too large)")
    left, right, frame = _calibration(fmt, path, calib)
    if extrinsic is not None:
        E = read_extrinsic(extrinsic) if isinstance(extrinsic, (str, Path)) else extrinsic
        E = np.asarray(E, dtype=np.float64)
        if E.shape != (4, 4):
            raise PoseFileError(f"extrinsic must be 4 x 4, got {E.shape}")
        right = E if right is None else right @ E
        frame += ", then the given extrinsic"
    return keys, T, fmt, left, right, frame


def _apply(T: np.ndarray, left: np.ndarray | None, right: np.ndarray | None) -> np.ndarray:
    if left is not None:
        T = left @ T
    if right is not None:
        T = T @ right
    return T


def read_poses(
    path: str | Path,
    poses_format: str | None = None,
    calib: str | Path | np.ndarray | None = "auto",
    extrinsic: np.ndarray | str | Path | None = None,
) -> tuple[np.ndarray, np.ndarray, str, str]:
    """A pose file's LiDAR poses: (keys [M], poses [M, 4, 4], format, frame description).

    `keys` are frame numbers for kitti (0..M-1), seconds for every other format
    (kitti360: frame index x 0.1 s). `calib`: "auto" (the format's published
    calibration; KITTI: calib.txt beside the file when it exists), "none", a file (KITTI
    calib.txt, KITTI-360 calibration folder) or a 4 x 4 array. `extrinsic`: a 4 x 4
    `T_frame<-lidar` (or a file holding one) applied after the calibration.
    """
    keys, T, fmt, left, right, frame = _read_raw(path, poses_format, calib, extrinsic)
    T = _apply(T, left, right)
    if not np.isfinite(T).all():
        # Finite numbers whose products overflow (1e300 in a pose and its calibration).
        raise PoseFileError(f"{path}: poses overflow to Inf or NaN (values far too large)")
    return keys, T, fmt, frame


def _name_time(name: str, fmt: str) -> float | None:
    """A scan's time (s) from its name, or None when the name holds none.

    `BAG#TOPIC@STAMP_NS` (a scan in a bag) gives its nanoseconds; an integer file stem is
    microseconds (nclt, oxford) or nanoseconds (mulran); for tum, a stem that is a
    decimal number is seconds, an integer of 16 digits microseconds, of 19 nanoseconds.
    kitti360 stems are frame numbers (x 0.1 s).
    """
    if "@" in name:
        stamp = name.rsplit("@", 1)[1]
        return int(stamp) * 1e-9 if _is_stamp(stamp) else None
    stem = Path(name).stem
    if fmt == "kitti360":
        # deferred: only this format's module loads (io.poses is on the query path)
        from disco_cli.io.poses.kitti360 import FRAME_S

        return int(stem) * FRAME_S if _is_stamp(stem) else None
    if fmt in _NAME_UNIT_S:
        return int(stem) * _NAME_UNIT_S[fmt] if _is_stamp(stem) else None
    if _is_stamp(stem):
        if len(stem) >= 18:
            return int(stem) * 1e-9
        if len(stem) >= 15:
            return int(stem) * 1e-6
        return float(stem)
    try:
        t = float(stem)
    except ValueError:
        return None
    return t if math.isfinite(t) else None


def _is_stamp(text: str) -> bool:
    """ASCII digits only (str.isdigit also takes '²' and other scripts' digits, which
    int() refuses), and few enough for a float (a name of 400 digits is no time)."""
    return text.isascii() and text.isdigit() and len(text) <= 30


def scan_times(scans: Sequence[str | Path], poses_format: str) -> np.ndarray:
    """The time (s) of each scan from its name (NaN where the name holds none)."""
    out = np.full(len(scans), np.nan)
    for i, s in enumerate(scans):
        t = _name_time(str(s), poses_format)
        if t is not None:
            out[i] = t
    return out


def _kitti_rows(names: list[str], n_rows: int, source: str) -> np.ndarray:
    """Row per scan: i when the counts agree, else (more rows than scans) the frame number
    in the file name (-1 when that row is not in the file). `PoseFileError` for fewer
    rows than scans, and for a name with no number."""
    if len(names) == n_rows:
        return np.arange(n_rows)
    if n_rows < len(names):
        # A KITTI file has a row for every frame: fewer rows than scans is another file.
        raise PoseFileError(f"{source}: {n_rows} poses for {len(names)} scans")
    rows = np.empty(len(names), dtype=np.int64)
    for i, p in enumerate(names):
        stem = Path(p).stem
        if not stem.isdigit():
            raise PoseFileError(
                f"{source}: {n_rows} rows for {len(names)} scans, and {p} has no frame "
                "number to pick its row by"
            )
        rows[i] = int(stem) if int(stem) < n_rows else -1
    return rows


class ScanPoser:
    """A pose file read once, giving poses to lists of scans (see `poses_for_scans`)."""

    def __init__(
        self,
        poses_file: str | Path,
        poses_format: str | None = None,
        calib: str | Path | np.ndarray | None = "auto",
        extrinsic: np.ndarray | str | Path | None = None,
        max_time_gap: float | None = None,
    ):
        self.source = str(poses_file)
        # Interpolation happens in the pose file's own frame (the body's motion), and the
        # calibration is applied afterwards: the LiDAR rides on the body.
        raw = _read_raw(poses_file, poses_format, calib, extrinsic)
        self.keys, self._T, self.format, self._left, self._right, self.frame = raw
        self.by_frame = self.format == "kitti"
        self.max_time_gap = (
            None
            if self.by_frame
            else (default_max_gap(self.keys) if max_time_gap is None else float(max_time_gap))
        )

    def __len__(self) -> int:
        return len(self._T)

    def poses(
        self, scans: Sequence[str | Path] | np.ndarray, times: np.ndarray | None = None
    ) -> tuple[np.ndarray, PoseReport]:
        """LiDAR poses `[N, 4, 4]` of the scans (NaN for none) and the report."""
        keys, T, fmt, source = self.keys, self._T, self.format, self.source
        by_time = isinstance(scans, np.ndarray) and scans.dtype.kind in "fiu"
        names = [] if by_time else [str(s) for s in scans]
        n = len(scans)
        out = np.full((n, 4, 4), np.nan)

        if self.by_frame:
            # KITTI rows are frames, not times: numbers given are frame numbers.
            if by_time:
                f = np.asarray(scans, dtype=np.float64)
                ok_f = (f == np.round(f)) & (f >= 0) & (f < len(T))
                rows = np.where(ok_f, f, -1).astype(np.int64)
                names = [f"frame {v:g}" for v in f]
            else:
                rows = _kitti_rows(names, len(T), source)
            ok = rows >= 0
            out[ok] = _apply(T[rows[ok]], self._left, self._right)
            missing = np.flatnonzero(~ok)
            report = PoseReport(
                source, fmt, n, int(ok.sum()), int(ok.sum()), 0, len(missing),
                tuple(names[i] for i in missing[:3]), None, self.frame,
            )  # fmt: skip
            return out, report

        if times is not None:
            t = np.asarray(times, dtype=np.float64).reshape(-1)
            if len(t) != n:
                raise PoseFileError(f"{len(t)} times for {n} scans")
        elif by_time:
            t = np.asarray(scans, dtype=np.float64)
        else:
            t = scan_times(names, fmt)
            if n and np.isnan(t).all():
                raise PoseFileError(
                    f"{source}: {fmt} poses are matched by time, and the scan names "
                    f"(e.g. {Path(names[0]).name}) hold no time; name scans by their stamp "
                    "or give their times"
                )
        gap = self.max_time_gap
        known = np.isfinite(t)
        tt = np.where(known, t, 0.0)
        poses, found = interpolate_poses(keys, T, tt, gap)
        found &= known
        out[found] = _apply(poses[found], self._left, self._right)
        # Exact: a pose stamp within EXACT_S of the scan's time (else interpolated).
        sorted_keys = np.sort(keys)
        hi = np.clip(np.searchsorted(sorted_keys, tt), 0, len(keys) - 1)
        lo = np.clip(hi - 1, 0, len(keys) - 1)
        dist = np.minimum(np.abs(sorted_keys[hi] - tt), np.abs(sorted_keys[lo] - tt))
        exact = found & (dist <= EXACT_S)
        missing = np.flatnonzero(~found)
        label = (lambda i: names[i]) if names else (lambda i: f"t={t[i]:.6f}")
        report = PoseReport(
            source, fmt, n, int(found.sum()), int(exact.sum()), int(found.sum() - exact.sum()),
            len(missing), tuple(label(i) for i in missing[:3]), gap, self.frame,
        )  # fmt: skip
        return out, report


def poses_for_scans(
    scans: Sequence[str | Path] | np.ndarray,
    poses_file: str | Path,
    poses_format: str | None = None,
    calib: str | Path | np.ndarray | None = "auto",
    extrinsic: np.ndarray | str | Path | None = None,
    max_time_gap: float | None = None,
    times: np.ndarray | None = None,
) -> tuple[np.ndarray, PoseReport]:
    """LiDAR poses `[N, 4, 4]` (`T_world<-lidar`, NaN for a scan without a pose) and a report.

    `scans`: scan paths or names (times come from the names; see `scan_times`), or an
    array of times in seconds. `times` overrides the times of named scans (e.g. a
    `times.txt`). `poses_format`: one of `POSE_FORMATS`, else guessed from the file.
    `calib`, `extrinsic`: see `read_poses`. `max_time_gap` (s): the farthest a pose
    may be from a scan's time to be used (exact matches always are); default three
    median periods of the pose file. Frame-numbered KITTI poses ignore `times`, and
    take an array of numbers as frame numbers.
    """
    poser = ScanPoser(poses_file, poses_format, calib, extrinsic, max_time_gap)
    return poser.poses(scans, times)


# The pose files a scan folder may hold beside its scans, in the order they are looked for.
_BESIDE = ("poses.txt", "global_pose.csv", "groundtruth_*.csv", "pointcloud_locations_20m.csv")


def find_pose_file(folder: str | Path) -> Path | None:
    """The pose file in a scan folder: `poses.txt` (KITTI, KITTI-360), `global_pose.csv`
    (MulRan), `groundtruth_*.csv` (NCLT; also `../ground_truth/groundtruth_<folder>.csv`)
    or `pointcloud_locations_20m.csv` (Oxford); None when there is none.
    `PoseFileError` when a pattern matches several files."""
    folder = Path(folder)
    for pattern in _BESIDE:
        found = sorted(p for p in folder.glob(pattern) if p.is_file())
        if len(found) > 1:
            names = ", ".join(p.name for p in found)
            raise PoseFileError(f"{folder}: several pose files ({names}); pass --poses")
        if found:
            return found[0]
    # NCLT as downloaded: ground_truth/groundtruth_<date>.csv beside the <date>/ sessions.
    nclt = folder.parent / "ground_truth" / f"groundtruth_{folder.name}.csv"
    return nclt if nclt.is_file() else None


def calib_arg(value: str | Path | None) -> str | Path:
    """A command's `--calib` value: None -> "auto", "none" -> "none", else the path."""
    if value is None:
        return "auto"
    if str(value).lower() in ("none", "auto"):
        return str(value).lower()
    return Path(value)
