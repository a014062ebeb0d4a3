"""Oxford RobotCar as the PointNetVLAD benchmark gives it: submap locations in a CSV.

`pointcloud_locations_20m.csv` (test submaps, in `pointcloud_20m/`) and
`pointcloud_locations_20m_10overlap.csv` (training submaps, in
`pointcloud_20m_10overlap/`) hold a header `timestamp,northing,easting` and one row per
submap: its time in microseconds (also its file name, `<timestamp>.bin`) and its UTM
position in metres. There is no heading and no height: a submap's pose here is the
translation (x = northing, y = easting, z = 0) with no rotation, so place-recognition
metrics hold but yaw errors mean nothing (Uy and Lee, "PointNetVLAD", CVPR 2018).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import PoseFileError
from disco_cli.io.poses._text import has_header, numeric_table, read_lines, split_fields

NAME_PREFIX = "pointcloud_locations"
UNIT_S = 1e-6  # timestamps and submap names are microseconds


def read_oxford_locations(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N] seconds, poses [N, 4, 4]: x = northing, y = easting, no rotation)."""
    lines = read_lines(path)
    cols = 3
    if lines and has_header(lines[0]):
        names = [f.strip().lower() for f in split_fields(lines[0])]
        if names[:3] != ["timestamp", "northing", "easting"]:
            raise PoseFileError(
                f"{path}: header {lines[0]!r} is not PointNetVLAD's 'timestamp,northing,easting'"
            )
        cols = len(names)  # some copies add an altitude column, which is ignored
    table, _ = numeric_table(path, cols, "submap locations")
    T = np.tile(np.eye(4), (len(table), 1, 1))
    T[:, 0, 3], T[:, 1, 3] = table[:, 1], table[:, 2]
    return table[:, 0] * UNIT_S, T


def write_oxford_locations(path: str | Path, stamps_us: np.ndarray, northing_easting) -> None:
    """Write a PointNetVLAD locations CSV (header, then timestamp,northing,easting)."""
    ne = np.asarray(northing_easting, dtype=np.float64).reshape(-1, 2)
    rows = [f"{int(t)},{n:.6f},{e:.6f}\n" for t, (n, e) in zip(stamps_us, ne)]
    Path(path).write_text("timestamp,northing,easting\n" + "".join(rows))
