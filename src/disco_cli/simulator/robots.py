"""The robots of later sessions: how each differs from session 00's (sensor, mount
height and tilt, driving line), drawn per session from `RobotParams`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.simulator.sensors import Sensor, get_sensor


@dataclass(frozen=True)
class RobotParams:
    """How the robots of later sessions differ from session 00's, drawn per session.

    The pose in poses.txt is the sensor's: it includes the mount's height and tilt.
    """

    height_m: tuple[float, float] | None = None  # mount height above the ground (range)
    tilt_deg: float = 0.0  # the mount's roll and pitch, each within +-tilt_deg
    offset_m: float | None = None  # sideways from session 00's driving line, up to this
    sensor: str | None = None  # a sensor name, uniform-N, hdl64like-N, or "random"
    # Each scan moved by up to this along and across its driving line (uniform, per scan).
    jitter_m: float = 0.0
    # Each scan LO..HI m to the side of session 00's line (uniform, per scan; one side
    # per session; replaces offset_m; the road must be wide enough: nothing keeps the
    # line on it).
    side_m: tuple[float, float] | None = None

    def check(self) -> None:
        if self.height_m is not None:
            lo, hi = self.height_m
            if not 0.3 <= lo <= hi <= 3.0:
                raise DiscoError("--robot-height must be a range within 0.3..3 m")
        if not 0.0 <= self.tilt_deg <= 10.0:
            raise DiscoError("--robot-tilt must be within 0..10 degrees")
        if self.offset_m is not None and not 0.0 <= self.offset_m <= MAX_OFFSET_M + 1.5:
            raise DiscoError(f"--robot-offset must be within 0..{MAX_OFFSET_M + 1.5:g} m")
        if not 0.0 <= self.jitter_m <= MAX_JITTER_M:
            raise DiscoError(f"--robot-jitter must be within 0..{MAX_JITTER_M:g} m")
        if self.side_m is not None:
            lo, hi = self.side_m
            if not 0.0 <= lo <= hi <= MAX_SIDE_M:
                raise DiscoError(f"--robot-side must be a range within 0..{MAX_SIDE_M:g} m")
            if self.offset_m is not None:
                raise DiscoError("give --robot-offset or --robot-side, not both")
        if self.sensor not in (None, "random"):
            get_sensor(self.sensor)

    def to_dict(self) -> dict:
        out: dict = {"tilt_deg": self.tilt_deg}
        if self.height_m is not None:
            out["height_m"] = list(self.height_m)
        if self.offset_m is not None:
            out["offset_m"] = self.offset_m
        if self.sensor is not None:
            out["sensor"] = self.sensor
        if self.jitter_m:
            out["jitter_m"] = self.jitter_m
        if self.side_m is not None:
            out["side_m"] = list(self.side_m)
        return out


MAX_OFFSET_M = 2.5  # how far right (or left) of the centre line a robot may drive
MAX_JITTER_M = 5.0
MAX_SIDE_M = 12.0
RANDOM_BEAMS = (16, 32, 64, 128)


def draw_robot(
    robot: RobotParams, seed: int, k: int, base: Sensor, offset0: float, reverse: bool
) -> tuple[Sensor, float, float, float, float | None]:
    """Session k's sensor, mount height, roll, pitch (deg) and offset (None: its own)."""
    rng = np.random.default_rng([seed, 30, k])
    sensor = base
    if robot.sensor == "random":
        layout = ("uniform", "hdl64like")[int(rng.integers(2))]
        sensor = get_sensor(f"{layout}-{int(rng.choice(RANDOM_BEAMS))}")
    elif robot.sensor is not None:
        sensor = get_sensor(robot.sensor)
    height = sensor.mount_height if robot.height_m is None else float(rng.uniform(*robot.height_m))
    roll, pitch = (float(v) for v in rng.uniform(-robot.tilt_deg, robot.tilt_deg, 2))
    offset = None
    if robot.offset_m is not None:
        # Session 00 drives offset0 right of the centre line; this session, d away from
        # that line: right of its own heading, which is the other side when reversed.
        d = float(rng.uniform(0.0, robot.offset_m))
        centre = -offset0 if reverse else offset0
        options = [centre + d, centre - d]
        fits = [o for o in options if abs(o) <= MAX_OFFSET_M]
        offset = fits[int(rng.integers(len(fits)))] if fits else min(options, key=abs)
        offset = float(np.clip(offset, -MAX_OFFSET_M, MAX_OFFSET_M))
    if robot.side_m is not None:
        # LO to the side of session 00's line, towards the centre line (the wider the
        # road, the more room); each scan then moves up to HI - LO further
        # (`jitter_stations`).
        centre = -offset0 if reverse else offset0
        offset = centre + _side_sign(centre) * robot.side_m[0]
    return sensor, height, roll, pitch, offset


def _side_sign(centre: float) -> float:
    """Which way (+1: right) a robot with --robot-side moves from session 00's line."""
    return -1.0 if centre > 0 else 1.0


def jitter_stations(
    robot: RobotParams | None,
    seed: int,
    k: int,
    stations: np.ndarray,
    lateral: np.ndarray,
    centre: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Session k's stations (along its line, m) and lateral offsets (right of it, m),
    each moved by up to `robot.jitter_m` (uniform, per scan) and, with `side_m`, by
    0..HI - LO further from session 00's line (`centre`: that line, m right of the
    centre line in this session's direction)."""
    if robot is None:
        return stations, lateral
    n = len(stations)
    if robot.side_m is not None:
        lo, hi = robot.side_m
        extra = np.random.default_rng([seed, 32, k]).uniform(0.0, hi - lo, n)
        lateral = lateral + _side_sign(centre) * extra
    if robot.jitter_m:
        rng = np.random.default_rng([seed, 31, k])
        j = float(robot.jitter_m)
        stations, lateral = stations + rng.uniform(-j, j, n), lateral + rng.uniform(-j, j, n)
    return stations, lateral
