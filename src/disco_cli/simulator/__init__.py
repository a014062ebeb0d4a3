"""The synthetic LiDAR world: a procedural town, sensor models and driving sessions.

The code lives in modules named for their job: `session` (driving sessions, ray
casting, noise, writing the files), `world` (the town: `layout`, `scenery` and
`changes` between sessions, `movers` within one), `robots` (how later sessions'
robots differ), `routes` (where the car drives) and `sensors` (beam patterns).
"""

from __future__ import annotations

from disco_cli.simulator.params import ChangeParams
from disco_cli.simulator.robots import RobotParams
from disco_cli.simulator.sensors import SENSORS, Sensor, get_sensor
from disco_cli.simulator.session import (
    SimulatedSession,
    cast,
    finish_scan,
    plan_sessions,
    scan,
    simulate,
    sweep_poses,
)
from disco_cli.simulator.world import Town, TownParams

__all__ = [
    "simulate",
    "scan",
    "cast",
    "sweep_poses",
    "plan_sessions",
    "finish_scan",
    "Town",
    "TownParams",
    "ChangeParams",
    "RobotParams",
    "Sensor",
    "SENSORS",
    "get_sensor",
    "SimulatedSession",
]
