"""Point-cloud augmentations: another sensor, another mounting, a blocked view.

Each function takes a scan `[N, 4]` (or `[N, 3]`) float32 in the sensor frame and returns
a new array; none moves the sensor in x-y or turns it about z, so a scan's pose (x, y,
heading) stays its ground truth. Training draws them through `augment_scan`; the
out-of-distribution suite (benchmarks/ood_suite.py) uses the same functions to make
real and simulated queries hard.

- `decimate_beams`: keep every k-th laser ring (a 64-beam scan seen as a 16-beam one).
- `drop_points`: keep a random share of the points (range dropout, sparser sensors).
- `occlude_wedge`: remove the points in one azimuth wedge (a truck beside the car, a
  sensor mounted behind a pillar).
- `tilt`: rotate about the sensor's x and y axes (a sensor mounted off level, a car
  on a crowned road or braking).
- `shift_z`: move the points up or down (another mounting height).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "AugmentConfig",
    "augment_scan",
    "decimate_beams",
    "drop_points",
    "occlude_wedge",
    "scan_rings",
    "shift_z",
    "tilt",
]

# A scan whose rings come out shorter than this (points per ring) is not in firing order.
_MIN_RING_POINTS = 50


def scan_rings(points: np.ndarray) -> np.ndarray | None:
    """Laser ring of each point, from the firing order, or None if the scan is not ordered.

    Spinning LiDARs (KITTI's HDL-64E, disco's simulator) store a scan ring by ring, each
    ring a counter-clockwise turn; measured in [0, 360), the azimuth then drops by almost a
    full turn exactly once per ring. Shuffled or merged clouds give implausibly short
    rings, and None.
    """
    if len(points) < _MIN_RING_POINTS:
        return None
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    starts = np.flatnonzero(np.diff(az) < -180.0) + 1
    lengths = np.diff(np.r_[0, starts, len(points)])
    if len(lengths) > 256 or np.median(lengths) < _MIN_RING_POINTS:
        return None
    ring = np.zeros(len(points), np.int64)
    ring[starts] = 1
    return np.cumsum(ring)


def decimate_beams(
    points: np.ndarray, beams: int, rng: np.random.Generator | None = None
) -> np.ndarray:
    """The scan as a sensor with about `beams` rings would see it: every k-th ring kept.

    k = round(rings / beams), at a random phase when `rng` is given. An unordered scan
    (no rings found) is cut into 4 * beams equal elevation bands instead, of which every
    fourth is kept. A scan with no more rings than `beams` is returned unchanged.
    """
    phase_rng = rng if rng is not None else np.random.default_rng(0)
    ring = scan_rings(points)
    if ring is None:
        el = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
        lo, hi = float(el.min()), float(el.max())
        bands = 4 * beams
        ring = np.minimum(((el - lo) / max(hi - lo, 1e-9) * bands).astype(np.int64), bands - 1)
        k, n = 4, bands
    else:
        n = int(ring.max()) + 1
        k = int(round(n / beams))
    if k <= 1:
        return points.copy()
    phase = int(phase_rng.integers(0, k)) if rng is not None else 0
    return points[ring % k == phase].copy()


def drop_points(points: np.ndarray, keep: float, rng: np.random.Generator) -> np.ndarray:
    """A random `keep` share of the points."""
    return points[rng.random(len(points)) < keep].copy()


def occlude_wedge(points: np.ndarray, start_deg: float, width_deg: float) -> np.ndarray:
    """The scan without the points whose azimuth lies in [start, start + width) degrees."""
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    inside = np.mod(az - start_deg, 360.0) < width_deg
    return points[~inside].copy()


def tilt(points: np.ndarray, roll_deg: float, pitch_deg: float) -> np.ndarray:
    """Points rotated by R_y(pitch) R_x(roll): the scan of a sensor tilted by the inverse."""
    r, p = np.radians(roll_deg), np.radians(pitch_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    out = points.astype(np.float32, copy=True)
    out[:, :3] = (points[:, :3].astype(np.float64) @ (ry @ rx).T).astype(np.float32)
    return out


def shift_z(points: np.ndarray, dz: float) -> np.ndarray:
    """Points moved by dz metres along z (a sensor mounted dz lower)."""
    out = points.astype(np.float32, copy=True)
    out[:, 2] += np.float32(dz)
    return out


@dataclass(frozen=True)
class AugmentConfig:
    """What `augment_scan` draws; each part applies with its own probability."""

    decimate_p: float = 0.5  # keep every k-th ring, towards 16 beams
    decimate_beams: tuple[int, ...] = (16,)
    drop_p: float = 0.5  # keep a uniform share in drop_keep of the points
    drop_keep: tuple[float, float] = (0.5, 0.9)
    wedge_p: float = 0.3  # remove one wedge of wedge_deg degrees
    wedge_deg: tuple[float, float] = (30.0, 90.0)
    tilt_p: float = 0.5  # roll and pitch uniform in +-tilt_deg
    tilt_deg: float = 3.0
    z_p: float = 0.5  # shift uniform in +-z_m
    z_m: float = 0.3

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def augment_scan(
    points: np.ndarray, rng: np.random.Generator, config: AugmentConfig | None = None
) -> np.ndarray:
    """One random variant of a scan (see `AugmentConfig`); its pose is the scan's own."""
    c = config or AugmentConfig()
    out = points
    if rng.random() < c.decimate_p:
        out = decimate_beams(out, int(rng.choice(c.decimate_beams)), rng)
    if rng.random() < c.drop_p:
        out = drop_points(out, float(rng.uniform(*c.drop_keep)), rng)
    if rng.random() < c.wedge_p:
        out = occlude_wedge(out, float(rng.uniform(0, 360)), float(rng.uniform(*c.wedge_deg)))
    if rng.random() < c.tilt_p:
        roll, pitch = rng.uniform(-c.tilt_deg, c.tilt_deg, size=2)
        out = tilt(out, float(roll), float(pitch))
    if rng.random() < c.z_p:
        out = shift_z(out, float(rng.uniform(-c.z_m, c.z_m)))
    return out if out is not points else points.copy()
