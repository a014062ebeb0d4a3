"""Oxford RobotCar submaps of the PointNetVLAD benchmark: `<timestamp>.bin`, 4096 points
of float64 x, y, z (24 bytes each), no intensity.

PointNetVLAD removed the ground, kept 4096 points and shifted and scaled each submap to
zero mean within [-1, 1] (Uy and Lee, CVPR 2018), so the coordinates are not metres:
see docs/formats.md for the BEV settings that suit them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.readers._common import assemble, check_record_size

RECORD_BYTES = 24  # 3 x float64


def read(path: Path) -> np.ndarray:
    """The submap as float32 `N x 4` (x, y, z as stored, intensity 0)."""
    try:
        check_record_size(path, path.stat().st_size, RECORD_BYTES, "float64 x, y, z")
        xyz = np.fromfile(path, dtype="<f8").reshape(-1, 3)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    return assemble(path, xyz[:, 0], xyz[:, 1], xyz[:, 2], None)
