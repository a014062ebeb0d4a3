"""The polar multi-layer bird's-eye view (BEV) of a LiDAR scan, DiSCO's input.

`polar_bev(points, config)` voxelizes one scan into a float32 array
`[heights, rings, sectors]` (C-contiguous); `polar_bev_batch` does many scans on
several threads. The work is done in C++ (`disco_cli._core`); this module checks
the input, converts it only when C++ cannot read it in place, and owns the
configuration.

Binning, in double precision (see docs/bev.md), with r = sqrt(x^2 + y^2):

- a point is kept when it is finite, `min_range <= r < max_range` and
  `z_min <= z < z_max`;
- `ring = floor(r / (max_range / rings))`;
- `sector = floor(theta / (2 pi / sectors))` with `theta = atan2(y, x)`, plus 2 pi
  when negative: sector 0 starts at +x and sectors grow counter-clockwise (toward
  +y), so rotating a scan by `+k * 360 / sectors` degrees about z rolls the BEV by
  `+k` along the last axis (`np.roll(bev, k, axis=-1)`);
- `height = floor((z - z_min) / ((z_max - z_min) / heights))`;
- each index is clamped into range, so a point that rounds onto a far edge
  (theta -> 2 pi) lands in the last cell instead of outside.

Modes: `occupancy` (1 where a cell holds a point), `density` (the cell's point
count divided by the largest cell count of the scan, so in [0, 1]; exact for up
to 2^24 points per cell) and `max_height` (Scan Context: one layer, shape
`[1, rings, sectors]`, holding `z - z_min` of the cell's top point, so an empty
cell, like a cell whose top point sits exactly at z_min, is 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError

MODES = ("occupancy", "density", "max_height")

__all__ = [
    "MODES",
    "BEVConfig",
    "BEVConfigError",
    "BEVInputError",
    "BEVInputTypeError",
    "polar_bev",
    "polar_bev_batch",
]


class BEVConfigError(DiscoError, ValueError):
    """A BEV configuration value or key is invalid."""


class BEVInputError(DiscoError, ValueError):
    """Points of the wrong shape for the voxelizer."""


class BEVInputTypeError(DiscoError, TypeError):
    """Points of a type the voxelizer cannot read (not a float array)."""


@dataclass(frozen=True)
class BEVConfig:
    """Size and extent of the polar BEV grid (metres, sensor frame).

    The default height window starts just above the ground for a car-mounted
    sensor about 1.7 m up (removing the ground by a height filter, as the DiSCO
    paper does) and spans 20 m in 20 layers; 40 rings out to 80 m, 120 sectors
    of 3 degrees; points nearer than 3 m (the ego vehicle) are dropped.
    """

    rings: int = 40
    sectors: int = 120
    heights: int = 20
    max_range: float = 80.0
    min_range: float = 3.0
    z_min: float = -1.5
    z_max: float = 18.5
    mode: str = "occupancy"

    def __post_init__(self) -> None:
        for name in ("rings", "sectors", "heights"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise BEVConfigError(f"BEVConfig.{name} must be an integer, got {value!r}")
            if not 1 <= value <= 1_000_000:
                raise BEVConfigError(f"BEVConfig.{name} must be in 1..1000000, got {value}")
            object.__setattr__(self, name, int(value))
        for name in ("max_range", "min_range", "z_min", "z_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(
                value, (int, float, np.integer, np.floating)
            ):
                raise BEVConfigError(f"BEVConfig.{name} must be a number, got {value!r}")
            if not np.isfinite(value) or abs(value) > 1e9:
                raise BEVConfigError(
                    f"BEVConfig.{name} must be finite and at most 1e9 in size, got {value}"
                )
            object.__setattr__(self, name, float(value))
        if not 0.0 <= self.min_range < self.max_range:
            raise BEVConfigError(
                f"BEVConfig needs 0 <= min_range < max_range, got min_range={self.min_range}, "
                f"max_range={self.max_range}"
            )
        if not self.z_min < self.z_max:
            raise BEVConfigError(
                f"BEVConfig needs z_min < z_max, got z_min={self.z_min}, z_max={self.z_max}"
            )
        if self.mode not in MODES:
            raise BEVConfigError(
                f"BEVConfig.mode must be one of {', '.join(MODES)}; got {self.mode!r}"
            )
        if self.rings * self.sectors * self.heights > 2**30:
            raise BEVConfigError("BEVConfig has too many cells (rings * sectors * heights > 2^30)")

    @property
    def layers(self) -> int:
        """Layers of the output: `heights`, or 1 for `max_height`."""
        return 1 if self.mode == "max_height" else self.heights

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of one BEV: (layers, rings, sectors)."""
        return (self.layers, self.rings, self.sectors)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BEVConfig:
        """Build from a mapping (e.g. a TOML table); missing keys take defaults."""
        if not isinstance(data, Mapping):
            raise BEVConfigError(f"BEVConfig.from_dict needs a mapping, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            known_keys = ", ".join(sorted(known))
            raise BEVConfigError(
                f"unknown BEVConfig key(s): {', '.join(unknown)} (known: {known_keys})"
            )
        return cls(**data)


@lru_cache(maxsize=32)
def _core_config(config: BEVConfig):
    """The C++ config struct for `config` (built once per distinct config)."""
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    core = _core.BEVConfig()
    core.rings, core.sectors, core.heights = config.rings, config.sectors, config.heights
    core.max_range, core.min_range = config.max_range, config.min_range
    core.z_min, core.z_max = config.z_min, config.z_max
    core.mode = getattr(_core.BEVMode, config.mode)
    return core


def _readable_in_place(points: np.ndarray) -> bool:
    """Whether C++ can read `points` as they are: native float32/float64, whole-element
    positive strides, aligned."""
    if points.dtype not in (np.float32, np.float64) or not points.dtype.isnative:
        return False
    if not points.flags.aligned:
        return False
    item = points.itemsize
    rows_stride, cols_stride = points.strides
    if points.shape[0] > 1 and (rows_stride <= 0 or rows_stride % item):
        return False
    return points.shape[0] == 0 or (cols_stride > 0 and cols_stride % item == 0)


def _prepare(points: Any, what: str = "points") -> np.ndarray:
    """Check `points` and return an array C++ reads in place, converting only if needed."""
    if not isinstance(points, np.ndarray):
        try:
            points = np.asarray(points)
        except (ValueError, TypeError) as exc:
            raise BEVInputTypeError(f"{what}: not convertible to an array ({exc})") from None
    if points.dtype.kind != "f":
        raise BEVInputTypeError(
            f"{what} must be a float32 or float64 array, got dtype {points.dtype}"
        )
    if points.ndim != 2 or points.shape[1] < 3:
        raise BEVInputError(f"{what} must be an N x 3 (or wider) array, got shape {points.shape}")
    if _readable_in_place(points):
        return points
    # One conversion, of the three columns used: float16 -> float32, longdouble -> float64.
    dtype = np.float32 if points.itemsize <= 4 else np.float64
    return np.ascontiguousarray(points[:, :3], dtype=dtype)


def polar_bev(points: Any, config: BEVConfig | None = None) -> np.ndarray:
    """The polar BEV of one scan: float32 `config.shape`, C-contiguous.

    `points` is N x 3 or wider (x, y, z first; extra columns ignored), float32 or
    float64. A float32 or float64 array with ordinary strides, such as a KITTI scan
    from `np.fromfile(f, np.float32).reshape(-1, 4)`, is read in place, not copied.
    NaN and Inf points are dropped; no points give an all-zero BEV. Binning and
    modes: see the module docstring.
    """
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    config = config if config is not None else BEVConfig()
    if not isinstance(config, BEVConfig):
        raise BEVConfigError(f"config must be a BEVConfig, got {type(config).__name__}")
    return _core.polar_bev(_prepare(points), _core_config(config))


def polar_bev_batch(
    scans: Sequence[Any], config: BEVConfig | None = None, threads: int = 0
) -> np.ndarray:
    """The BEVs of many scans, `[B, *config.shape]` float32, each equal to `polar_bev`.

    Scans are voxelized in C++ on `threads` threads (0: all cores) with the GIL
    released.
    """
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    config = config if config is not None else BEVConfig()
    if not isinstance(config, BEVConfig):
        raise BEVConfigError(f"config must be a BEVConfig, got {type(config).__name__}")
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
        raise BEVConfigError(f"threads must be an integer >= 0, got {threads!r}")
    if isinstance(scans, np.ndarray) and scans.ndim == 2:
        raise BEVInputError(
            "polar_bev_batch takes a list of scans; got one N x C array (use polar_bev)"
        )
    prepared = [_prepare(s, f"scans[{i}]") for i, s in enumerate(scans)]
    return _core.polar_bev_batch(prepared, _core_config(config), int(threads))
