"""NCLT velodyne_sync scans: .bin files of 8-byte little-endian records.

Each record is uint16 x, y, z, uint8 intensity, uint8 laser id; a coordinate
in metres is `raw * 0.005 - 100` (NCLT's published conversion).

NCLT's Velodyne frame has z pointing down (x forward, y right, z down, like its body
frame; NCLT's own plotting script negates z). The reader turns it 180 degrees about x,
`(x, y, z) -> (x, -y, -z)`, so scans come out z up like every other format's; the NCLT
pose reader (`disco_cli.io.poses.nclt`) gives the poses of this same z-up frame. This is
the one place that turn is made for scans.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import assemble, check_record_size

SCALE = 0.005  # metres per count
OFFSET = -100.0  # metres
RECORD = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"), ("laser", "u1")])


# 180 degrees about x: NCLT's z-down Velodyne frame -> the z-up frame disco uses.
TURN = (1.0, -1.0, -1.0)


def read(path: Path) -> np.ndarray:
    """The scan as float32 `N x 4` in the z-up sensor frame: metres, and intensity as the
    raw 0-255 value."""
    try:
        check_record_size(path, path.stat().st_size, RECORD.itemsize, "uint16 x, y, z, uint8 i, l")
        raw = np.fromfile(path, dtype=RECORD)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    # Scale in float64 so the 5 mm grid lands on the nearest float32.
    xyz = [(raw[c].astype(np.float64) * SCALE + OFFSET) * t for c, t in zip("xyz", TURN)]
    return assemble(path, *xyz, raw["intensity"], drop_nonfinite=False)
