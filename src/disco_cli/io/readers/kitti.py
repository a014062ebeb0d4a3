"""KITTI and MulRan Velodyne scans: .bin files of little-endian float32 x, y, z, intensity."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError
from disco_cli.io.readers._common import check_record_size

RECORD_BYTES = 16  # 4 x float32


def read(path: Path) -> np.ndarray:
    """The scan as read from disk, `N x 4` float32; no copy, so it can reach C++ as is."""
    try:
        check_record_size(path, path.stat().st_size, RECORD_BYTES, "float32 x, y, z, intensity")
        return np.fromfile(path, dtype="<f4").reshape(-1, 4)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
