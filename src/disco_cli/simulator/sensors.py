"""Beam patterns and error models of the simulated spinning LiDARs.

Elevation angles follow the data sheets: HDL-32E 32 beams evenly over
-30.67..+10.67 deg; HDL-64E an upper block of 32 beams over +2..-8.33 deg and a
lower block over -8.83..-24.9 deg; VLP-16 16 beams over -15..+15 deg; OS1-64 64
beams evenly over about -16.6..+16.6 deg. The azimuth steps are chosen so that a
32-beam scan of a street holds about 30k points (real sensors give 2-4 times more;
fewer points keep simulation and training fast while the BEV is just as full).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from disco_cli.errors import DiscoError


@dataclass(frozen=True)
class Sensor:
    name: str
    elevations_deg: tuple[float, ...]  # beam elevations, top to bottom
    azimuth_step_deg: float
    max_range: float  # m
    min_range: float  # m: returns closer than this are dropped (the car itself)
    range_noise: float  # m, standard deviation
    dropout: float  # probability that a return is lost, before material effects
    mount_height: float  # m above the ground
    rate_hz: float = 10.0

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def columns(self) -> int:
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def rays(self) -> int:
        return self.beams * self.columns

    def directions(self) -> np.ndarray:
        """Unit ray directions in the sensor frame, `[beams * columns, 3]` float32.

        Beam by beam (top beam first), each a full turn from azimuth 0 (x forward)
        counter-clockwise, as KITTI scans are ordered.
        """
        el = np.radians(np.asarray(self.elevations_deg, dtype=np.float64))[:, None]
        az = np.radians(np.arange(self.columns) * (360.0 / self.columns))[None, :]
        d = np.stack(
            np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)),
            axis=-1,
        )
        return d.reshape(-1, 3).astype(np.float32)

    def fractions(self) -> np.ndarray:
        """When in the sweep each ray fires, as a fraction of the sweep, `[rays]` float32.

        The head spins clockwise seen from above (like Velodyne and Ouster sensors),
        starting and ending behind the car: the rear ray fires at 0, the left at 1/4,
        the forward at 1/2 (the moment of the scan's pose), the right at 3/4.
        """
        az = np.arange(self.columns) * (360.0 / self.columns)
        f = np.mod(180.0 - az, 360.0) / 360.0
        return np.tile(f, self.beams).astype(np.float32)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["elevations_deg"] = [round(float(e), 4) for e in self.elevations_deg]
        return out


def _even(top: float, bottom: float, n: int) -> tuple[float, ...]:
    return tuple(float(round(v, 4)) for v in np.linspace(top, bottom, n))


SENSORS: dict[str, Sensor] = {
    "hdl32": Sensor(
        name="hdl32",
        elevations_deg=_even(10.67, -30.67, 32),
        azimuth_step_deg=0.3,
        max_range=100.0,
        min_range=1.0,
        range_noise=0.02,
        dropout=0.01,
        mount_height=1.8,
    ),
    "hdl64": Sensor(
        name="hdl64",
        elevations_deg=_even(2.0, -8.33, 32) + _even(-8.83, -24.9, 32),
        azimuth_step_deg=0.2,
        max_range=120.0,
        min_range=2.5,
        range_noise=0.02,
        dropout=0.01,
        mount_height=1.73,
    ),
    "vlp16": Sensor(
        name="vlp16",
        elevations_deg=_even(15.0, -15.0, 16),
        azimuth_step_deg=0.2,
        max_range=100.0,
        min_range=1.0,
        range_noise=0.03,
        dropout=0.01,
        mount_height=1.85,
    ),
    "os1-64": Sensor(
        name="os1-64",
        elevations_deg=_even(16.6, -16.6, 64),
        azimuth_step_deg=360.0 / 1024,
        max_range=120.0,
        min_range=1.0,
        range_noise=0.03,
        dropout=0.015,
        mount_height=1.85,
    ),
}


LAYOUTS = ("uniform", "hdl64like")
BEAMS = (16, 128)  # the fewest and the most beams of a made-up sensor


def made_sensor(layout: str, beams: int) -> Sensor:
    """A sensor of `beams` beams: `uniform` spreads them evenly over +15..-25 deg;
    `hdl64like` puts half over +2..-8.33 deg and half over -8.83..-24.9 deg, as the
    HDL-64E does (dense near the horizon)."""
    if layout not in LAYOUTS or not BEAMS[0] <= beams <= BEAMS[1]:
        raise DiscoError(
            f"a made-up sensor needs a layout of {', '.join(LAYOUTS)} and "
            f"{BEAMS[0]}-{BEAMS[1]} beams, not {layout}-{beams}"
        )
    if layout == "uniform":
        elevations = _even(15.0, -25.0, beams)
    else:
        upper = beams // 2
        elevations = _even(2.0, -8.33, upper) + _even(-8.83, -24.9, beams - upper)
    step = 0.2 if beams <= 16 else 0.3 if beams <= 48 else 0.35
    return Sensor(
        name=f"{layout}-{beams}",
        elevations_deg=elevations,
        azimuth_step_deg=step,
        max_range=100.0 if beams <= 32 else 120.0,
        min_range=1.0,
        range_noise=0.02,
        dropout=0.01,
        mount_height=1.8,
    )


def get_sensor(name: str) -> Sensor:
    """A named sensor (`SENSORS`), or a made-up one: `uniform-N` or `hdl64like-N`
    (N beams, 16-128; see `made_sensor`)."""
    if name in SENSORS:
        return SENSORS[name]
    layout, _, beams = name.rpartition("-")
    if layout in LAYOUTS and beams.isdigit():
        return made_sensor(layout, int(beams))
    raise DiscoError(
        f"unknown sensor {name!r}; choose one of {', '.join(SENSORS)}, "
        "uniform-N or hdl64like-N (N = 16..128 beams)"
    )
