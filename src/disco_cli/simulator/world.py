"""A procedural town for the simulated LiDAR: roads, buildings, walls, trees, poles, cars.

`Town` puts together its parts, each in a module named for what it does:
`layout` (street network, ground), `scenery` (what stands along the streets, as
`styles` has it), `changes` (what differs between sessions), `movers` (what moves
within one); the primitives and objects are in `objects`, the parameters in
`params`.

Everything is made of three primitives that the C++ ray caster knows (boxes
turned about z, vertical cylinders, vertical ellipsoids) over a gently tilted
ground plane.
"""

from __future__ import annotations

import numpy as np

from disco_cli.simulator.changes import Changes, SessionWorld
from disco_cli.simulator.objects import BOX, CYLINDER, ELLIPSOID, Material, Prims
from disco_cli.simulator.params import TownParams
from disco_cli.simulator.scenery import Occupancy


class Town(Changes):
    """A generated town: street network, static scenery and changeable things."""

    def __init__(self, seed: int, params: TownParams | None = None):
        self.seed = int(seed)
        self.params = params or TownParams()
        rng = np.random.default_rng([self.seed, 1])
        p = self.params
        # Gentle tilt of the ground: z = a x + b y.
        ang = rng.uniform(0, 2 * np.pi)
        slope = rng.uniform(0.3, 1.0) * p.max_slope
        self.ground = (float(slope * np.cos(ang)), float(slope * np.sin(ang)), 0.0)
        self._make_network(rng)
        self.static = Prims()
        self.objects: list[str] = []  # the class of each object (see objects.Prims.obj)
        self._latent: list[Prims] = []
        self._pool_cache = None
        self._texture: tuple[float, float, float, np.ndarray] | None = None
        self._last_built = False  # whether the last lot got a building
        self._seg: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._changeable: list[tuple[float, Prims]] = []  # (presence probability, things)
        self._parking: list[tuple[np.ndarray, float, float]] = []  # (x y, yaw, occupancy)
        self._occupied = Occupancy(self.bounds(margin=p.outskirts_m + 10))
        for k in range(len(self.streets)):
            for side in (1.0, -1.0):
                self._dress_side(np.random.default_rng([self.seed, 2, k, int(side > 0)]), k, side)
        for n in range(len(self.nodes)):
            self._dress_junction(np.random.default_rng([self.seed, 3, n]), n)
        self._outskirts(np.random.default_rng([self.seed, 4]))
        if p.terrain == "varied":
            b = self._builder()
            self._crown_roads(b)
            self.static.extend(b.prims)

    def describe(self) -> dict:
        out = {
            "seed": self.seed,
            "params": self.params.to_dict(),
            "ground_plane": list(self.ground),
            "junctions": len(self.nodes),
            "streets": len(self.streets),
            "static_primitives": len(self.static.rows),
            "changeable_groups": len(self._changeable),
            "parking_spots": len(self._parking),
        }
        if self.params.style != "grid" or self.params.change is not None:
            out["objects"] = {c: self.objects.count(c) for c in sorted(set(self.objects))}
        return out


def wall_world(distance: float, height: float = 10.0, length: float = 40.0) -> SessionWorld:
    """A flat ground and one wall facing the origin at x = `distance` (for tests)."""
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    table = np.array(
        [[BOX, distance + 0.25, 0.0, height / 2, 0.25, length / 2, height / 2, 0.0, 1.0]]
    )
    caster = _core.RaycastWorld(table, 0.0, 0.0, 0.0, 4.0)
    return SessionWorld(caster, np.array([0.5], np.float32), np.zeros(1, np.float32), table)


def primitives_world(
    table: np.ndarray, ground: tuple[float, float, float] = (0.0, 0.0, 0.0), cell_size: float = 4.0
) -> SessionWorld:
    """A world from an explicit primitive table `[N, 9]` (for tests and experiments)."""
    # deferred: the package imports without the compiled core (docs/architecture.md)
    from disco_cli import _core

    table = np.asarray(table, dtype=np.float64).reshape(-1, 9)
    caster = _core.RaycastWorld(table, *ground, cell_size)
    n = len(table)
    return SessionWorld(caster, np.full(n, 0.5, np.float32), np.zeros(n, np.float32), table)


__all__ = [
    "Town",
    "TownParams",
    "SessionWorld",
    "Material",
    "wall_world",
    "primitives_world",
    "BOX",
    "CYLINDER",
    "ELLIPSOID",
]
