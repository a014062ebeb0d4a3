"""Is a headerless .bin really in the layout it was read with?

KITTI, NCLT and Oxford `.bin` files carry no header: any file whose size is a multiple
of the record reads without error in the wrong layout, and the scan that comes out is
noise that a search still matches (with a confident yaw). These checks refuse such a
read, naming --scan-format. They are built from what the three layouts give on correct
scans and on each other's bytes (tests/test_scan_format_check.py measures both on the
bundled samples written in each layout):

- correct scans: no point beyond 500 m or not a number, 99 % or more of the points within
  80 m of the sensor across the ground, 55 % or more within 10 m;
- a KITTI scan read as NCLT: 16-18 % within 80 m, none within 10 m; an Oxford submap
  read as NCLT: 18-21 % within 80 m, under 0.5 % within 10 m;
- an NCLT scan or an Oxford submap read as KITTI, or a KITTI scan read as Oxford: 65-99 %
  of the points beyond 500 m or not numbers, and those spread over 4.4 decades of
  distance or more (10th to 90th percentile), where a scan moved far away into a map's
  frame spans less than one;
- an NCLT scan read as Oxford: every point within a micrometre of the sensor.

A real scan always holds the ground and objects close by (the lowest beams of a car's or
robot's LiDAR reach the ground within a few metres). The thresholds below sit between
the two: a refusal needs more than half the points beyond 500 m (wrong reads: 65 % or
more; correct: none) spread over more than 2 decades, or more than half not numbers,
or fewer than half within 80 m (wrong: 21 % at most; correct: 99 %) together with fewer
than 2 % within 10 m (wrong: under 0.5 %; correct: 55 % or more), or more than half at
the sensor. A scan moved whole into a far frame passes, to be refused later for having
no point in range.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError

# The layouts checked: the headerless ones (npy, pcd, ply and bags describe themselves).
CHECKED = ("kitti", "nclt", "oxford")

FAR_M = 500.0  # no LiDAR scan reaches this far
MOST = 0.5  # more than this share of points beyond FAR_M (or NaN) is not a scan...
SPREAD_DECADES = 2.0  # ...when their distances spread over more decades than this
BEV_M = 80.0  # the default BEV's radius
IN_BEV = 0.5  # a scan has at least this share of its points within BEV_M...
NEAR_M = 10.0
NEAR = 0.02  # ...or at least this share within NEAR_M (either is enough)
AT_SENSOR_M = 1e-3  # a point this close to the sensor is the sensor itself
# Shares of a handful of points say nothing; the smallest real scans here are Oxford's
# 4096-point submaps (a test's few-point file is left alone).
MIN_POINTS = 1000
# The shares above are judged on an even stride of at most this many points: the
# margins (99 % against 21 %, none against 65 %) dwarf a sample's error, and every
# query reads its scan through here (the whole scan cost about 4 ms at 120k points).
SAMPLE = 4096


def layout_problem(points: np.ndarray) -> str | None:
    """Why `points` (N x 4, from a layout in CHECKED) cannot be a LiDAR scan, or None
    (always None under MIN_POINTS points)."""
    if len(points) < MIN_POINTS:
        return None
    xyz = points[:: max(1, len(points) // SAMPLE), :3]
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(xyz).all(axis=1)
        size = np.abs(xyz).max(axis=1, initial=0.0)
        if (~finite).mean() > MOST:
            return f"{(~finite).mean():.0%} of its points are not numbers"
        far = finite & (size > FAR_M)
        if (far | ~finite).mean() > MOST:
            # Bytes read in the wrong layout give sizes over many decades; a scan moved
            # into a far frame (a map's, UTM) keeps its own few: "no points in range" later.
            low, high = np.percentile(np.log10(size[far]), [10, 90])
            if high - low > SPREAD_DECADES:
                return (
                    f"{(far | ~finite).mean():.0%} of its points lie beyond {FAR_M:g} m or are "
                    f"not numbers, from {10**low:.0e} m to {10**high:.0e} m"
                )
        r = np.hypot(xyz[:, 0], xyz[:, 1])
        r = np.where(finite, r, np.inf)
        in_bev, near = (r <= BEV_M).mean(), (r <= NEAR_M).mean()
        # (A scan moved whole beyond FAR_M is left to "no points in range".)
        if in_bev < IN_BEV and near < NEAR and not (far | ~finite).mean() > MOST:
            return (
                f"only {in_bev:.0%} of its points lie within {BEV_M:g} m of the sensor "
                f"and {near:.1%} within {NEAR_M:g} m"
            )
        at_sensor = (np.abs(xyz).max(axis=1, initial=0.0) < AT_SENSOR_M) & finite
        if at_sensor.mean() > MOST:
            return f"{at_sensor.mean():.0%} of its points lie at the sensor (within 1 mm)"
    return None


def check_layout(path: Path, points: np.ndarray, fmt: str) -> None:
    """Refuse, as one `ScanReadError` line naming --scan-format, a scan whose points
    show that its bytes are not in the `fmt` layout."""
    problem = layout_problem(points)
    if problem is not None:
        raise ScanReadError(
            path,
            f"read as {_NAMES.get(fmt, fmt)} it is no LiDAR scan ({problem}); "
            f"pass the right --scan-format (kitti, nclt, oxford)",
        )


_NAMES = {"kitti": "KITTI", "nclt": "NCLT", "oxford": "Oxford"}
