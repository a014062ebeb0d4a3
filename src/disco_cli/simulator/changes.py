"""What changes between sessions: parked cars, small things, trees, foliage, hedges,
fences and buildings (what moves within a session is in `movers`).

A session's world is the static town plus that session's draw of the changeable
things; `SessionWorld.at(t)` adds the movers where they are at time `t`.

Two models of change between sessions:
- the classic draw (no `TownParams.change`): each session draws afresh which parked
  cars, bins, benches, bushes, signs and some street trees are there, and scales every
  crown's chance to stop a ray by its own foliage factor;
- the change model (`TownParams.change`): session 00 is the reference, and each later
  session changes a set share of each class of objects (parked cars, trees, hedges,
  fences, street furniture, buildings and containers), each in one of its class's
  ways (`ACTIONS`); new hedges, fences, buildings and containers appear where none
  stood, about as many as go. With every share 0 every session sees session 00's
  world.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from disco_cli.simulator.movers import Movers
from disco_cli.simulator.objects import ELLIPSOID, Builder, Material, Prims, car
from disco_cli.simulator.params import CHANGE_CLASSES

if TYPE_CHECKING:
    from disco_cli.simulator.world import Town

# How an object of each class changes, with the share of each way.
ACTIONS: dict[str, tuple[tuple[str, float], ...]] = {
    "cars": (("gone", 0.5), ("other car", 0.5)),
    "trees": (("felled", 0.2), ("grown", 0.2), ("shrunk", 0.2), ("bare", 0.4)),
    "hedges": (("cut down", 0.5), ("trimmed", 0.5)),
    "fences": (("taken down", 0.5), ("rebuilt", 0.5)),
    "furniture": (("gone", 0.5), ("moved", 0.5)),
    "buildings": (("demolished", 1.0),),
}
GONE = {"gone", "felled", "cut down", "taken down", "demolished"}


@dataclass
class SessionWorld:
    """The scene of one session, ready for ray casting.

    `movers` (cars driving, people walking) are not in `table`; `at(t, xy)` gives
    the world at time `t` with them in place (and none within a few metres of the
    sensor at `xy`, where they would run into the car).
    """

    caster: object  # disco_cli._core.RaycastWorld
    reflectivity: np.ndarray  # [primitives] float32
    dropout: np.ndarray  # [primitives] float32
    table: np.ndarray  # [primitives, 9]: kind, cx, cy, cz, hx, hy, hz, yaw, hit_prob
    movers: np.ndarray | None = None  # [M, 12], see Town._movers
    town: Town | None = None
    objects: np.ndarray | None = None  # [primitives] object id (Town.objects), -1: none

    def at(self, t: float, xy: np.ndarray | None = None, keep_clear_m: float = 8.0) -> SessionWorld:
        if self.movers is None or len(self.movers) == 0 or self.town is None:
            return self
        # deferred: the package imports without the compiled core (docs/architecture.md)
        from disco_cli import _core

        rows, refl, drop = self.town.mover_rows(self.movers, t, xy, keep_clear_m)
        table = np.concatenate([self.table, rows])
        caster = _core.RaycastWorld(table, *self.town.ground, self.town.params.cell_size_m)
        return SessionWorld(
            caster,
            np.concatenate([self.reflectivity, refl]),
            np.concatenate([self.dropout, drop]),
            table,
            objects=None
            if self.objects is None
            else np.concatenate([self.objects, np.full(len(rows), -1, np.int64)]),
        )


class Changes(Movers):
    """Each session's draw of the changeable things, and the movers (a part of `Town`)."""

    objects: list[str]
    _pool_cache: _Pool | None

    # -- the classic draw ---------------------------------------------------------
    def session_world(self, session: int) -> SessionWorld:
        """The static town plus this session's parked cars and changeable things."""
        # deferred: the package imports without the compiled core (docs/architecture.md)
        from disco_cli import _core

        if self.params.change is not None:
            return self._changed_world(int(session))
        rng = np.random.default_rng([self.seed, 5, int(session)])
        prims = Prims()
        prims.extend(self.static)
        for prob, things in self._changeable:
            if rng.random() < prob:
                prims.extend(things)
        b = self._builder()
        for c, yaw, occupancy in self._parking:
            if rng.random() < occupancy:
                jitter = rng.uniform(-0.8, 0.8) * np.array([np.cos(yaw), np.sin(yaw)])
                car(rng, b, c + jitter, yaw + rng.normal(0, 0.03))
        prims.extend(b.prims)
        table = np.array(prims.rows, dtype=np.float64).reshape(-1, 9)
        # Leaves come and go: this session's foliage is denser or sparser.
        leafy = (table[:, 0] == ELLIPSOID) & (table[:, 8] < 1.0)
        table[leafy, 8] = np.clip(table[leafy, 8] * rng.uniform(*self.params.foliage), 0.05, 0.95)
        a, bb, cc = self.ground
        caster = _core.RaycastWorld(table, a, bb, cc, self.params.cell_size_m)
        movers = self._movers(np.random.default_rng([self.seed, 10, int(session)]))
        return SessionWorld(
            caster,
            np.array(prims.refl, np.float32),
            np.array(prims.drop, np.float32),
            table,
            movers,
            self,
        )

    def _pool(self) -> _Pool:
        """Every object any session may show, and which of them session 00 has."""
        if self._pool_cache is not None:
            return self._pool_cache
        prims = Prims()
        prims.extend(self.static)
        rng = np.random.default_rng([self.seed, 20])
        present = {}
        for prob, things in self._changeable:
            here = bool(rng.random() < prob)
            for o in set(things.obj) - {-1}:
                present[o] = here
            prims.extend(things)
        for things in self._latent:
            for o in set(things.obj) - {-1}:
                present[o] = False
            prims.extend(things)
        sites = self._builder()
        self._construction_sites(np.random.default_rng([self.seed, 24]), sites)
        for o in set(sites.prims.obj) - {-1}:
            present[o] = False
        prims.extend(sites.prims)
        # Parked cars: one per spot, and the car that parks there instead.
        b, alt = self._builder(), self._builder()
        others: dict[int, tuple[int, int]] = {}
        for i, (c, yaw, occupancy) in enumerate(self._parking):
            crng = np.random.default_rng([self.seed, 21, i])
            here = bool(crng.random() < occupancy)
            for builder in (b, alt):
                m = builder.mark()
                jitter = crng.uniform(-0.8, 0.8) * np.array([np.cos(yaw), np.sin(yaw)])
                car(crng, builder, c + jitter, yaw + crng.normal(0, 0.03))
                if builder is b:
                    oid = builder.tag(m, "cars")
                    present[oid] = here
                else:
                    others[oid] = (m, builder.mark())
        prims.extend(b.prims)
        table = np.array(prims.rows, np.float64).reshape(-1, 9)
        obj = np.array(prims.obj, np.int64)
        n = len(self.objects)
        present0 = np.ones(n, bool)  # the static town's objects are there
        for o, here in present.items():
            present0[o] = here
        self._pool_cache = _Pool(
            table,
            np.array(prims.refl, np.float32),
            np.array(prims.drop, np.float32),
            obj,
            present0,
            np.array(alt.prims.rows, np.float64).reshape(-1, 9),
            np.array(alt.prims.refl, np.float32),
            np.array(alt.prims.drop, np.float32),
            others,
        )
        return self._pool_cache

    def _construction_sites(self, rng: np.random.Generator, b: Builder) -> None:
        """Places where a house, a hall or a stack of containers may go up."""
        x0, y0, x1, y1 = self.bounds(margin=20.0)
        n_buildings = sum(1 for c in self.objects if c == "buildings")
        want, made = max(4, n_buildings // 5), 0
        for _ in range(50 * want):
            if made >= want:
                break
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            if not 2.0 < self.road_clearance(c[None])[0] < 25.0:
                continue
            yaw = rng.uniform(0, np.pi)
            if rng.random() < 0.5:  # containers, one to three high
                w, d = 6.06, 2.44
                if not self._site_free(c, w / 2, d / 2, yaw):
                    continue
                m = b.mark()
                for level in range(rng.integers(1, 4)):
                    mat = Material(rng.uniform(0.15, 0.7))
                    b.box(c, w, d, yaw, 2.6 * level, 2.6 * (level + 1), mat)
            else:
                w, d = rng.uniform(8, 20), rng.uniform(8, 16)
                if not self._site_free(c, w / 2, d / 2, yaw):
                    continue
                m = b.mark()
                b.box(c, w, d, yaw, 0.0, rng.uniform(4, 14), Material(rng.uniform(0.15, 0.5)))
            self._occupied.mark(c, w / 2, d / 2, yaw)
            b.tag(m, "buildings")
            made += 1

    def session_changes(self, session: int) -> dict[int, str]:
        """What the change model does to each object in `session`: {object id: action},
        where an object that appears has "new"; session 00 changes nothing."""
        pool = self._pool()
        change = self.params.change
        if session == 0 or change is None:
            return {}
        classes = np.array(self.objects)
        rng = np.random.default_rng([self.seed, 22, session])
        u = rng.random((len(classes), 2))  # drawn for every object: decisions stay apart
        out: dict[int, str] = {}
        for cls in CHANGE_CLASSES:
            ids = np.flatnonzero(classes == cls)
            if len(ids) == 0:
                continue
            rate = change.rate(cls)
            names = [a for a, _ in ACTIONS[cls]]
            cum = np.cumsum([w for _, w in ACTIONS[cls]])
            here = ids[pool.present0[ids]]
            for o in here[u[here, 0] < rate]:
                out[int(o)] = names[min(int(np.searchsorted(cum, u[o, 1])), len(names) - 1)]
            # About as many new ones as go, where the class has room for them (a car
            # in an empty spot, a hedge where none stood, a construction site).
            latent = ids[~pool.present0[ids]]
            gone_share = sum(w for a, w in ACTIONS[cls] if a in GONE)
            if len(latent):
                q = min(1.0, rate * gone_share * len(here) / len(latent))
                for o in latent[u[latent, 0] < q]:
                    out[int(o)] = "new"
        return out

    def _changed_world(self, session: int) -> SessionWorld:
        # deferred: the package imports without the compiled core (docs/architecture.md)
        from disco_cli import _core

        pool = self._pool()
        actions = self.session_changes(session)
        shown = pool.present0.copy()
        table, refl, drop, obj = pool.table.copy(), pool.refl, pool.drop, pool.obj
        rng = np.random.default_rng([self.seed, 26, session])
        keep = np.ones(len(table), bool)
        extra_rows, extra_refl, extra_drop, extra_obj = [], [], [], []
        a, b, _ = self.ground
        for o, action in sorted(actions.items()):
            rows = np.flatnonzero(obj == o)
            if action == "new":
                shown[o] = True
            elif action in GONE:
                shown[o] = False
            elif action == "other car":
                shown[o] = False
                lo, hi = pool.other_rows[o]
                extra_rows.append(pool.alt_table[lo:hi])
                extra_refl.append(pool.alt_refl[lo:hi])
                extra_drop.append(pool.alt_drop[lo:hi])
                extra_obj.append(np.full(hi - lo, o, np.int64))
            elif action in ("grown", "shrunk"):
                crown = rows[(table[rows, 0] == ELLIPSOID) & (table[rows, 8] < 1.0)]
                f = rng.uniform(1.15, 1.4) if action == "grown" else rng.uniform(0.6, 0.85)
                bottom = table[crown, 3] - table[crown, 6]
                table[crown, 4:7] *= f
                table[crown, 3] = bottom + table[crown, 6]
            elif action == "bare":  # the leaves are gone: most rays pass the crown
                crown = rows[(table[rows, 0] == ELLIPSOID) & (table[rows, 8] < 1.0)]
                table[crown, 8] *= rng.uniform(0.2, 0.4)
            elif action in ("trimmed", "rebuilt"):
                f = rng.uniform(0.5, 0.75) if action == "trimmed" else rng.uniform(0.6, 1.4)
                bottom = table[rows, 3] - table[rows, 6]
                table[rows, 6] = ((2 * table[rows, 6] - 0.3) * f + 0.3) / 2  # 0.3 m sunk
                table[rows, 3] = bottom + table[rows, 6]
                if action == "rebuilt":
                    table[rows, 8] = rng.uniform(0.25, 0.6)
            elif action == "moved":
                ang, dist = rng.uniform(0, 2 * np.pi), rng.uniform(1.0, 3.0)
                dx, dy = dist * np.cos(ang), dist * np.sin(ang)
                table[rows, 1] += dx
                table[rows, 2] += dy
                table[rows, 3] += a * dx + b * dy
        keep = (obj < 0) | shown[np.maximum(obj, 0)]
        table = np.concatenate([table[keep], *extra_rows]).reshape(-1, 9)
        refl = np.concatenate([refl[keep], *extra_refl]).astype(np.float32)
        drop = np.concatenate([drop[keep], *extra_drop]).astype(np.float32)
        obj = np.concatenate([obj[keep], *extra_obj]).astype(np.int64)
        caster = _core.RaycastWorld(table, *self.ground, self.params.cell_size_m)
        movers = self._movers(np.random.default_rng([self.seed, 10, session]))
        cyclists = self._cyclists(np.random.default_rng([self.seed, 23, session]))
        return SessionWorld(
            caster, refl, drop, table, np.concatenate([movers, cyclists]), self, obj
        )


@dataclass
class _Pool:
    """The change model's objects: every row any session may show."""

    table: np.ndarray  # [R, 9]
    refl: np.ndarray  # [R]
    drop: np.ndarray  # [R]
    obj: np.ndarray  # [R] object id, -1: part of no object
    present0: np.ndarray  # [objects] whether session 00 has it
    alt_table: np.ndarray  # the cars that park instead, rows
    alt_refl: np.ndarray
    alt_drop: np.ndarray
    other_rows: dict[int, tuple[int, int]]  # car object id -> its stand-in's rows
