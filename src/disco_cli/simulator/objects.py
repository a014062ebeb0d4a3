"""The three primitives of the ray caster and the objects made of them.

A primitive row is `kind, cx, cy, cz, hx, hy, hz, yaw, hit_prob`: boxes turned
about z, vertical cylinders and vertical ellipsoids. `Builder` stands them on a
town's ground; `tree`, `car` and `small_object` draw one object each.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from disco_cli.simulator.world import Town

BOX, CYLINDER, ELLIPSOID = 0, 1, 2


@dataclass
class Material:
    reflectivity: float  # 0..1, the return's intensity at normal incidence
    dropout: float = 0.0  # extra chance that a return is lost (glass, dark paint)


@dataclass
class Prims:
    """Primitives under construction: the table rows, their materials and objects.

    `obj` names the object (an index into `Town.objects`) that each row belongs to,
    -1 for rows that belong to none (sidewalks, lights, walls): the change model
    moves, reshapes or removes whole objects.
    """

    rows: list[list[float]] = field(default_factory=list)
    refl: list[float] = field(default_factory=list)
    drop: list[float] = field(default_factory=list)
    obj: list[int] = field(default_factory=list)

    def extend(self, other: Prims) -> None:
        self.rows += other.rows
        self.refl += other.refl
        self.drop += other.drop
        self.obj += other.obj


class Builder:
    """Adds primitives standing on the town's ground."""

    def __init__(self, town: Town):
        self.town = town
        self.prims = Prims()

    def _add(self, row: list[float], mat: Material) -> None:
        self.prims.rows.append([float(v) for v in row])
        self.prims.refl.append(float(mat.reflectivity))
        self.prims.drop.append(float(mat.dropout))
        self.prims.obj.append(-1)

    def mark(self) -> int:
        """Where the next object starts (see `tag`)."""
        return len(self.prims.rows)

    def tag(self, start: int, cls: str) -> int:
        """Name the rows added since `start` one object of class `cls`; returns its id."""
        if start >= len(self.prims.rows):
            return -1
        oid = len(self.town.objects)
        self.town.objects.append(cls)
        for i in range(start, len(self.prims.rows)):
            self.prims.obj[i] = oid
        return oid

    def box(
        self,
        c: np.ndarray,
        length: float,
        width: float,
        yaw: float,
        z0: float,
        z1: float,
        mat: Material,
        hit_prob: float = 1.0,
    ) -> None:
        """A box `length` along `yaw`, `width` across, from z0 to z1 above the ground."""
        g = float(self.town.ground_z(c[0], c[1]))
        lo = g + z0 - (0.3 if z0 <= 0 else 0.0)  # sink into the tilted ground: no gaps
        hi = g + z1
        self._add(
            [BOX, c[0], c[1], (lo + hi) / 2, length / 2, width / 2, (hi - lo) / 2, yaw, hit_prob],
            mat,
        )

    def cylinder(self, c: np.ndarray, radius: float, z0: float, z1: float, mat: Material) -> None:
        g = float(self.town.ground_z(c[0], c[1]))
        lo, hi = g + z0 - (0.3 if z0 <= 0 else 0.0), g + z1
        self._add(
            [CYLINDER, c[0], c[1], (lo + hi) / 2, radius, radius, (hi - lo) / 2, 0.0, 1.0], mat
        )

    def ellipsoid(
        self,
        c: np.ndarray,
        radius: float,
        z_centre: float,
        half_height: float,
        mat: Material,
        hit_prob: float,
    ) -> None:
        g = float(self.town.ground_z(c[0], c[1]))
        self._add(
            [ELLIPSOID, c[0], c[1], g + z_centre, radius, radius, half_height, 0.0, hit_prob], mat
        )


def tree(rng: np.random.Generator, b: Builder, c: np.ndarray, size: float) -> None:
    """A trunk and a partly see-through crown (sometimes two lobes)."""
    trunk_h = rng.uniform(1.8, 3.5) * size
    b.cylinder(c, rng.uniform(0.12, 0.3) * size, 0.0, trunk_h + 0.5, Material(0.35))
    radius = rng.uniform(2.0, 4.5) * size
    half_h = radius * rng.uniform(0.8, 1.5)
    prob = rng.uniform(0.45, 0.8)
    b.ellipsoid(c, radius, trunk_h + half_h * 0.8, half_h, Material(rng.uniform(0.4, 0.6)), prob)
    if rng.random() < 0.3:
        off = rng.normal(0, radius * 0.4, 2)
        b.ellipsoid(
            c + off, radius * 0.7, trunk_h + half_h * 1.6, half_h * 0.6, Material(0.4), prob
        )


def car(rng: np.random.Generator, b: Builder, c: np.ndarray, yaw: float) -> None:
    length, width = rng.uniform(3.8, 5.0), rng.uniform(1.65, 1.9)
    body_h = rng.uniform(0.9, 1.1)
    paint = Material(rng.choice([0.08, 0.2, 0.5, 0.8]), 0.03)
    b.box(c, length, width, yaw, 0.25, body_h, paint)
    cabin = length * rng.uniform(0.45, 0.65)
    shift = np.array([np.cos(yaw), np.sin(yaw)]) * rng.uniform(-0.4, 0.1)
    b.box(
        c + shift,
        cabin,
        width * 0.9,
        yaw,
        body_h,
        body_h + rng.uniform(0.4, 0.8),
        Material(0.1, 0.4),
    )  # glass: many lost returns
    # Wheels: what a low beam sees under the body.
    for sx in (-1, 1):
        for sy in (-1, 1):
            w = c + np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]) @ np.array(
                [sx * (length / 2 - 0.75), sy * (width / 2 - 0.15)]
            )
            b.box(w, 0.6, 0.25, yaw, 0.0, 0.6, Material(0.05))


def small_object(rng: np.random.Generator, b: Builder, c: np.ndarray, yaw: float) -> None:
    kind = rng.integers(4)
    if kind == 0:  # bin
        b.cylinder(c, rng.uniform(0.25, 0.4), 0.0, rng.uniform(0.8, 1.1), Material(0.3))
    elif kind == 1:  # bench
        b.box(c, rng.uniform(1.5, 2.2), 0.6, yaw, 0.0, 0.8, Material(0.3))
    elif kind == 2:  # bush
        b.ellipsoid(c, rng.uniform(0.5, 1.2), 0.5, rng.uniform(0.4, 0.9), Material(0.4), 0.7)
    else:  # a sign on a post
        b.cylinder(c, 0.05, 0.0, 2.2, Material(0.4))
        b.box(c, 0.6, 0.05, yaw + np.pi / 2, 1.6, 2.2, Material(0.9))
