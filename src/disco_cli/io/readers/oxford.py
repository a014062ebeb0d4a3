"""Oxford RobotCar submaps of the PointNetVLAD benchmark: `<timestamp>.bin`, 4096 points
of float64 x, y, z (24 bytes each), no intensity.

PointNetVLAD's published submap script (submap_generation/generate_submaps.m in
github.com/mikacuy/pointnetvlad) built each submap from 20 m of the car's travel
(push-broom SICK LMS-151 scans in the vehicle frame at the submap's start: x forward,
y right, z down), removed the ground plane, kept 4096 points, centred them on their
centroid, scaled them by `0.5 / d` (d: the points' mean distance from the centroid,
so a scale of its own for every submap, not stored), negated all three coordinates and
dropped what fell outside [-1, 1]. So the coordinates are not metres, and the frame is
mirrored (x back, y left, z up).

The reader undoes what it can: it negates x again (x forward, y left, z up: a
right-handed, z-up frame) and multiplies by one scale for all submaps, `DEFAULT_SCALE`
metres per unit unless `scale(m)` sets another. The true per-submap scale is lost; see
docs/formats.md for why 20 m is the default.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.io.readers._common import assemble, check_record_size

RECORD_BYTES = 24  # 3 x float64
# Metres per normalized unit: [-1, 1] becomes [-20 m, 20 m] (an assumption: docs/formats.md).
DEFAULT_SCALE = 20.0
_scale = DEFAULT_SCALE


@contextmanager
def scale(metres: float | None) -> Iterator[None]:
    """Read submaps with `metres` per unit inside the block (None: the default)."""
    global _scale
    m = DEFAULT_SCALE if metres is None else float(metres)
    if not np.isfinite(m) or m <= 0:
        raise DiscoError(f"--oxford-scale must be a positive number of metres, got {metres}")
    before, _scale = _scale, m
    try:
        yield
    finally:
        _scale = before


def read(path: Path) -> np.ndarray:
    """The submap as float32 `N x 4`: x forward, y left, z up, in metres at the current
    scale; intensity 0."""
    try:
        check_record_size(path, path.stat().st_size, RECORD_BYTES, "float64 x, y, z")
        xyz = np.fromfile(path, dtype="<f8").reshape(-1, 3)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    m = _scale
    # A damaged value near float64's limit overflows to Inf here, and assemble drops it;
    # random bytes hold signalling NaNs, which warn "invalid value" when multiplied.
    with np.errstate(over="ignore", invalid="ignore"):
        x, y, z = -m * xyz[:, 0], m * xyz[:, 1], m * xyz[:, 2]
    return assemble(path, x, y, z, None)
