"""Helpers shared by the format modules: assembling the N x 4 result and its checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError

# Field names taken as the intensity channel, in order of preference
# (`scalar_intensity` is what CloudCompare writes).
INTENSITY_NAMES = ("intensity", "reflectance", "remission", "scalar_intensity")


def pick_intensity(names: list[str]) -> str | None:
    """The field to use as intensity, or None when there is none."""
    lowered = {n.lower(): n for n in names}
    for candidate in INTENSITY_NAMES:
        if candidate in lowered:
            return lowered[candidate]
    return None


def assemble(
    path: Path,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    intensity: np.ndarray | None,
    drop_nonfinite: bool = True,
) -> np.ndarray:
    """Stack columns into a float32 N x 4 array and check that it has points.

    Organized clouds (PCD, PLY from ROS tools) mark missing returns with NaN;
    those rows carry no geometry, so they are dropped here.
    """
    out = np.empty((len(x), 4), dtype=np.float32)
    # A value beyond float32's range becomes Inf (dropped below with NaN) without a
    # RuntimeWarning on the user's terminal.
    with np.errstate(over="ignore", invalid="ignore"):
        out[:, 0] = x
        out[:, 1] = y
        out[:, 2] = z
        out[:, 3] = 0.0 if intensity is None else intensity
    if drop_nonfinite:
        keep = np.isfinite(out[:, :3]).all(axis=1)
        if not keep.all():
            if not keep.any():
                raise ScanReadError(path, f"none of its {len(out)} points has finite x, y, z")
            out = out[keep]
    return check_not_empty(path, out)


def check_not_empty(path: Path, points: np.ndarray) -> np.ndarray:
    if len(points) == 0:
        raise ScanReadError(path, "the scan has no points")
    return points


def check_record_size(path: Path, size: int, record: int, layout: str) -> int:
    """The number of fixed-size records in a file of `size` bytes, or ScanReadError."""
    if size == 0:
        raise ScanReadError(path, "the file is empty (no points)")
    if size % record:
        raise ScanReadError(
            path,
            f"size {size} bytes is not a multiple of the {record}-byte record "
            f"({layout}): truncated or not this format",
        )
    return size // record
