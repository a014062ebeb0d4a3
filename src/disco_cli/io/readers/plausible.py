"""Is a headerless .bin really a LiDAR scan in the layout it was read with?

KITTI, NCLT and Oxford `.bin` files carry no header: any file whose size is a multiple
of the record reads without error, in the wrong layout or when it is no scan at all
(a text file, a dump, a file cut short), and the points that come out are noise that a
search still matches (with a confident yaw). These checks refuse such a read in one
line. They are built from what the three layouts give on correct scans and on each
other's bytes (tests/test_scan_format_check.py measures both on the bundled samples
written in each layout):

- correct scans: no point beyond 500 m, 99 % or more of the returns within 80 m of the
  sensor across the ground, 55 % or more within 10 m;
- a KITTI scan read as NCLT: 16-18 % within 80 m, none within 10 m; an Oxford submap
  read as NCLT: 18-21 % within 80 m, under 0.5 % within 10 m;
- an NCLT scan or an Oxford submap read as KITTI, or a KITTI scan read as Oxford: 65-99 %
  of the points beyond 500 m or not numbers, and those spread over 4.4 decades of
  distance or more (10th to 90th percentile), where a scan moved far away into a map's
  frame spans less than one;
- an NCLT scan read as Oxford: every point within a micrometre of the sensor;
- text read as any of them: printable characters, which no binary scan's first bytes
  are (float mantissas, NCLT's laser ids 0-31 and zero bytes fill them with control
  characters).

What a scan is, then:

- **returns**: a point is a return when its x, y, z are finite and it lies farther than
  1 mm from the sensor. Organized clouds mark "no return" with NaN or with zeros; up to
  MAX_NO_RETURN (90 %) of the points may be such non-returns. Real layouts hold far
  fewer (benchmarks/bench_layout_check.py): a KITTI HDL-64E scan leaves 12-15 % of its
  64 x 2010 image empty, the HDL-32E pair of ../shared/realdata stores 7.3 % of its
  points as zeros and leaves 9-12 % of its 32-ring image empty, the simulated HDL-32E
  11 % of its rays.
- **enough of them**: MIN_POINTS points in the file and MIN_POINTS returns. The
  smallest real scans here are PointNetVLAD's 4,096-point Oxford submaps (ground
  removed); a spinning LiDAR gives 15k-130k. A file cut short to a few records is
  refused, not matched.
- **their shape**: more than half the returns beyond 500 m, spread over more than 2
  decades, is a wrong layout (wrong reads: 65 % or more; correct: none); so is fewer
  than half within 80 m (wrong: 21 % at most; correct: 99 %) together with fewer than
  2 % within 10 m (wrong: under 0.5 %; correct: 55 % or more). A scan moved whole into a
  far frame passes, to be refused later for having no point in range.

The shares are judged on a random sample of SAMPLE points, the same positions (a
seeded draw) for every scan of a length: an even stride aliases with the periodic
patterns of organized clouds (every third point NaN, read with a stride of 6, showed
100 % NaN). A share's sampling error is under 2.5 % (3 sigma), against margins of 30 %
and more. Every query reads its scan through here: about 0.05 ms a scan, whatever its
size (benchmarks/bench_layout_check.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from disco_cli.errors import ScanReadError

# The layouts checked: the headerless ones (npy, pcd, ply and bags describe themselves).
CHECKED = ("kitti", "nclt", "oxford")

# The fewest points, and the fewest returns, a LiDAR scan has (Oxford's submaps: 4096).
MIN_POINTS = 1000
AT_SENSOR_M = 1e-3  # a point this close to the sensor is no return (organized clouds' 0)
# The largest share of points that may be no return (NaN, infinite or at the sensor).
MAX_NO_RETURN = 0.9
FAR_M = 500.0  # no LiDAR scan reaches this far
MOST = 0.5  # more than this share of returns beyond FAR_M is not a scan...
SPREAD_DECADES = 2.0  # ...when their distances spread over more decades than this
BEV_M = 80.0  # the default BEV's radius
IN_BEV = 0.5  # a scan has at least this share of its returns within BEV_M...
NEAR_M = 10.0
NEAR = 0.02  # ...or at least this share within NEAR_M (either is enough)
# The shares are judged on this many points drawn at random (all of a smaller scan).
SAMPLE = 4096
# Where the sample falls, as fractions of the scan's length: seeded, so a scan is judged
# the same way every time it is read.
_POSITIONS = np.sort(np.random.default_rng(20240406).random(SAMPLE))
# The bytes read from the head of a file to tell text from a binary scan.
TEXT_PROBE = 512
# Bytes that text holds none of: the control characters other than tab, newline,
# vertical tab, form feed and carriage return, and DEL.
_CONTROL = bytes([*range(0x00, 0x09), *range(0x0E, 0x20), 0x7F])


def layout_problem(points: np.ndarray) -> str | None:
    """Why `points` (N x 4, from a layout in CHECKED) cannot be a LiDAR scan, or None."""
    n = len(points)
    if n < MIN_POINTS:
        return f"only {n} points, where a LiDAR scan has {MIN_POINTS} or more: cut short?"
    sample = points.take((_POSITIONS * n).astype(np.intp), axis=0) if n > SAMPLE else points
    x, y, z = sample[:, 0], sample[:, 1], sample[:, 2]
    m = len(sample)
    with np.errstate(invalid="ignore", over="ignore"):
        # The largest |coordinate|: NaN when one is NaN, infinite when one is.
        size = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z))
        finite = size < np.inf
        returns = finite & (size >= AT_SENSOR_M)
        n_returns = np.count_nonzero(returns)
        if n_returns == 0 or 1.0 - n_returns / m > MAX_NO_RETURN or n * n_returns / m < MIN_POINTS:
            not_numbers = 1.0 - np.count_nonzero(finite) / m
            at_sensor = 1.0 - not_numbers - n_returns / m
            kinds = f"{not_numbers:.0%} not numbers, {at_sensor:.0%} at the sensor within 1 mm"
            if 1.0 - n_returns / m > MAX_NO_RETURN:
                return (
                    f"{1.0 - n_returns / m:.0%} of its points are no return ({kinds}), "
                    f"where a LiDAR scan has at most {MAX_NO_RETURN:.0%}"
                )
            return (
                f"only about {n * n_returns / m:.0f} of its {n} points are returns ({kinds}), "
                f"where a LiDAR scan has {MIN_POINTS} or more"
            )
        far = returns & (size > FAR_M)
        far_share = np.count_nonzero(far) / n_returns
        if far_share > MOST:
            # Bytes read in the wrong layout give sizes over many decades; a scan moved
            # into a far frame (a map's, UTM) keeps its own few: "no points in range" later.
            low, high = np.percentile(np.log10(size[far]), [10, 90])
            if high - low > SPREAD_DECADES:
                return (
                    f"{far_share:.0%} of its returns lie beyond {FAR_M:g} m, "
                    f"from {10**low:.0e} m to {10**high:.0e} m"
                )
            return None  # a scan moved whole beyond FAR_M: left to "no points in range"
        r2 = x * x + y * y
        in_bev = np.count_nonzero(returns & (r2 <= BEV_M**2)) / n_returns
        near = np.count_nonzero(returns & (r2 <= NEAR_M**2)) / n_returns
    if in_bev < IN_BEV and near < NEAR:
        return (
            f"only {in_bev:.0%} of its returns lie within {BEV_M:g} m of the sensor "
            f"and {near:.1%} within {NEAR_M:g} m"
        )
    return None


def is_text(head: bytes) -> bool:
    """True when the first bytes of a file hold no control character: text."""
    return bool(head) and len(head.translate(None, _CONTROL)) == len(head)


def check_layout(path: Path, points: np.ndarray, fmt: str) -> None:
    """Refuse, as one `ScanReadError` line, a file read in the `fmt` layout that is no
    LiDAR scan: text, too few points or returns, or points that show its bytes are in
    another layout (naming --scan-format)."""
    name = _NAMES.get(fmt, fmt)
    try:
        with open(path, "rb") as fh:
            head = fh.read(TEXT_PROBE)
    except OSError as exc:
        raise ScanReadError(path, f"cannot read: {exc.strerror or exc}") from None
    if is_text(head):
        raise ScanReadError(path, f"read as {name} it is no LiDAR scan: its first bytes are text")
    problem = layout_problem(points)
    if problem is None:
        return
    if len(points) < MIN_POINTS:  # cut short, whatever its layout
        raise ScanReadError(path, f"read as {name} it is no LiDAR scan ({problem})")
    raise ScanReadError(
        path,
        f"read as {name} it is no LiDAR scan ({problem}); "
        "pass the right --scan-format (kitti, nclt, oxford)",
    )


_NAMES = {"kitti": "KITTI", "nclt": "NCLT", "oxford": "Oxford"}
