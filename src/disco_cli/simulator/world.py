"""A procedural town for the simulated LiDAR: roads, buildings, walls, trees, poles, cars.

The town is a jittered grid of junctions joined by straight streets (some links
removed, so blocks differ in size and shape and the network has loops and
T-junctions). Every street side gets its own character (building heights,
setbacks, frontage walls or fences or hedges, tree rows, street lights, parking),
so that no two streets look alike and place recognition has something to find.

What the scene holds is split in two: the static town, and things that change
between sessions (parked cars, bins and benches, bushes, some trees). A session's
world is the static town plus that session's draw of the changeable things.

Everything is made of three primitives that the C++ ray caster knows (boxes
turned about z, vertical cylinders, vertical ellipsoids) over a gently tilted
ground plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from disco_cli.errors import DiscoError

BOX, CYLINDER, ELLIPSOID = 0, 1, 2
_GRASS = 0.3  # reflectivity of the ground off the roads


@dataclass
class TownParams:
    blocks_x: int = 4
    blocks_y: int = 4
    block_min_m: float = 55.0
    block_max_m: float = 95.0
    node_jitter_m: float = 6.0
    link_drop: float = 0.15  # share of inner links removed (keeps every junction >= 2 links)
    road_width_m: tuple[float, float] = (8.0, 13.0)
    sidewalk_m: tuple[float, float] = (1.8, 3.5)
    max_slope: float = 0.02  # ground gradient (2 % = gentle)
    outskirts_m: float = 70.0  # depth of the scattered trees and sheds around the town
    cell_size_m: float = 4.0  # ray-casting grid
    traffic_per_km: float = 8.0  # moving cars per km of street, each way
    pedestrians_per_km: float = 10.0  # people walking per km of sidewalk, each side
    foliage: tuple[float, float] = (0.6, 1.15)  # per-session factor on crowns' hit chance

    def to_dict(self) -> dict:
        return {
            f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
            for f in fields(self)
        }

    @classmethod
    def from_dict(cls, data: dict, source: str = "town parameters") -> TownParams:
        """Parameters from a dict (unknown keys and bad values raise DiscoError)."""
        known = {f.name: f for f in fields(cls)}
        unknown = set(data) - set(known)
        if unknown:
            raise DiscoError(f"{source}: unknown town parameters: {', '.join(sorted(unknown))}")
        default = cls()
        values = {}
        for key, value in data.items():
            want = getattr(default, key)
            if isinstance(want, tuple):
                ok = (
                    isinstance(value, (list, tuple))
                    and len(value) == 2
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
                )
                value = tuple(float(v) for v in value) if ok else value
            else:
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                if ok and isinstance(want, int) and float(value) != int(value):
                    ok = False
                value = type(want)(value) if ok else value
            if not ok:
                raise DiscoError(f"{source}: {key} = {value!r} is not like {want!r}")
            values[key] = value
        params = cls(**values)
        params.check(source)
        return params

    def check(self, source: str = "town parameters") -> None:
        """Raise DiscoError on values that cannot make a town."""
        problems = []
        if self.blocks_x < 1 or self.blocks_y < 1 or self.blocks_x * self.blocks_y > 400:
            problems.append("blocks_x and blocks_y must be >= 1 (at most 400 blocks)")
        if not 20 <= self.block_min_m <= self.block_max_m <= 1000:
            problems.append("need 20 <= block_min_m <= block_max_m <= 1000")
        for key in ("road_width_m", "sidewalk_m", "foliage"):
            lo, hi = getattr(self, key)
            if not 0 < lo <= hi:
                problems.append(f"{key} must be a range 0 < low <= high")
        if self.road_width_m[1] + 2 * self.sidewalk_m[1] >= self.block_min_m:
            problems.append("roads and sidewalks must be narrower than the smallest block")
        if not 0 <= self.link_drop < 1 or not 0 <= self.max_slope <= 0.2:
            problems.append("need 0 <= link_drop < 1 and 0 <= max_slope <= 0.2")
        if not 0 <= self.node_jitter_m < self.block_min_m / 4:
            problems.append("node_jitter_m must be within 0 .. block_min_m / 4")
        if self.cell_size_m <= 0.5 or self.outskirts_m < 0:
            problems.append("cell_size_m must be > 0.5 and outskirts_m >= 0")
        if self.traffic_per_km < 0 or self.pedestrians_per_km < 0:
            problems.append("traffic_per_km and pedestrians_per_km must be >= 0")
        if problems:
            raise DiscoError(f"{source}: " + "; ".join(problems))

    @classmethod
    def load(cls, path: str | Path) -> TownParams:
        """From a TOML file (keys at the top or under [town]) or a world.json."""
        import json

        import tomllib

        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise DiscoError(f"{path}: cannot read ({exc.strerror})") from None
        try:
            if path.suffix == ".json":
                data = json.loads(text)["town"]["params"]
            else:
                data = tomllib.loads(text)
                data = data.get("town", data)
        except (ValueError, KeyError, TypeError) as exc:
            raise DiscoError(f"{path}: not a town TOML or world.json ({exc})") from None
        if not isinstance(data, dict):
            raise DiscoError(f"{path}: not a town TOML or world.json")
        return cls.from_dict(data, str(path))


@dataclass
class Material:
    reflectivity: float  # 0..1, the return's intensity at normal incidence
    dropout: float = 0.0  # extra chance that a return is lost (glass, dark paint)


@dataclass
class _Prims:
    """Primitives under construction: the table rows and their materials."""

    rows: list[list[float]] = field(default_factory=list)
    refl: list[float] = field(default_factory=list)
    drop: list[float] = field(default_factory=list)

    def extend(self, other: _Prims) -> None:
        self.rows += other.rows
        self.refl += other.refl
        self.drop += other.drop


class Street:
    """One street (a link between two junctions) and its geometry."""

    def __init__(self, a: np.ndarray, b: np.ndarray, half_width: float, sidewalk: float):
        self.a, self.b = a, b
        self.half_width = half_width
        self.sidewalk = sidewalk
        v = b - a
        self.length = float(np.hypot(*v))
        self.dir = v / self.length
        self.left = np.array([-self.dir[1], self.dir[0]])
        self.yaw = float(np.arctan2(v[1], v[0]))


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

    def at(self, t: float, xy: np.ndarray | None = None, keep_clear_m: float = 8.0) -> SessionWorld:
        if self.movers is None or len(self.movers) == 0 or self.town is None:
            return self
        from disco_cli import _core

        rows, refl, drop = self.town.mover_rows(self.movers, t, xy, keep_clear_m)
        table = np.concatenate([self.table, rows])
        caster = _core.RaycastWorld(table, *self.town.ground, self.town.params.cell_size_m)
        return SessionWorld(
            caster,
            np.concatenate([self.reflectivity, refl]),
            np.concatenate([self.dropout, drop]),
            table,
        )


class Town:
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
        self.static = _Prims()
        self._texture: tuple[float, float, float, np.ndarray] | None = None
        self._last_built = False  # whether the last lot got a building
        self._seg: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._changeable: list[tuple[float, _Prims]] = []  # (presence probability, things)
        self._parking: list[tuple[np.ndarray, float, float]] = []  # (x y, yaw, occupancy)
        self._occupied = _Occupancy(self.bounds(margin=p.outskirts_m + 10))
        for k in range(len(self.streets)):
            for side in (1.0, -1.0):
                self._dress_side(np.random.default_rng([self.seed, 2, k, int(side > 0)]), k, side)
        for n in range(len(self.nodes)):
            self._dress_junction(np.random.default_rng([self.seed, 3, n]), n)
        self._outskirts(np.random.default_rng([self.seed, 4]))

    # -- network -------------------------------------------------------------
    def _make_network(self, rng: np.random.Generator) -> None:
        p = self.params
        if p.blocks_x < 1 or p.blocks_y < 1:
            raise DiscoError("a town needs at least one block in x and in y")
        xs = np.concatenate(
            [[0.0], np.cumsum(rng.uniform(p.block_min_m, p.block_max_m, p.blocks_x))]
        )
        ys = np.concatenate(
            [[0.0], np.cumsum(rng.uniform(p.block_min_m, p.block_max_m, p.blocks_y))]
        )
        nx, ny = len(xs), len(ys)
        gx, gy = np.meshgrid(xs - xs[-1] / 2, ys - ys[-1] / 2, indexing="ij")
        nodes = np.stack([gx.ravel(), gy.ravel()], axis=1)
        nodes += rng.uniform(-p.node_jitter_m, p.node_jitter_m, nodes.shape)
        idx = np.arange(nx * ny).reshape(nx, ny)
        links = [(int(idx[i, j]), int(idx[i + 1, j])) for i in range(nx - 1) for j in range(ny)]
        links += [(int(idx[i, j]), int(idx[i, j + 1])) for i in range(nx) for j in range(ny - 1)]
        # Remove some inner links, keeping the network connected with no dead ends.
        order = rng.permutation(len(links))
        keep = [True] * len(links)
        n_drop = int(round(p.link_drop * len(links)))
        dropped = 0
        for li in order:
            if dropped >= n_drop:
                break
            keep[li] = False
            kept = [links[i] for i in range(len(links)) if keep[i]]
            deg = np.bincount(np.array(kept).ravel(), minlength=len(nodes))
            if deg.min() < 2 or not _connected(len(nodes), kept):
                keep[li] = True
            else:
                dropped += 1
        self.nodes = nodes
        self.links = [links[i] for i in range(len(links)) if keep[i]]
        self.streets = []
        for u, v in self.links:
            half = rng.uniform(*p.road_width_m) / 2
            self.streets.append(Street(nodes[u], nodes[v], half, rng.uniform(*p.sidewalk_m)))
        # How far from a junction its streets' kerbs and scenery keep clear.
        self.node_clear = np.zeros(len(nodes))
        for (u, v), s in zip(self.links, self.streets):
            for n in (u, v):
                self.node_clear[n] = max(self.node_clear[n], s.half_width + s.sidewalk + 1.0)

    def bounds(self, margin: float = 0.0) -> tuple[float, float, float, float]:
        lo, hi = self.nodes.min(axis=0) - margin, self.nodes.max(axis=0) + margin
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def ground_z(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        a, b, c = self.ground
        return a * np.asarray(x) + b * np.asarray(y) + c

    def road_clearance(self, xy: np.ndarray) -> np.ndarray:
        """Distance (m) from points `[M, 2]` to the nearest kerb-plus-sidewalk edge.

        Negative inside a road or its sidewalks.
        """
        xy = np.atleast_2d(xy)
        if self._seg is None:
            a = np.array([s.a for s in self.streets])
            v = np.array([s.b - s.a for s in self.streets])
            w = np.array([s.half_width + s.sidewalk for s in self.streets])
            self._seg = (a, v, w)
        a, v, w = self._seg
        rel = xy[:, None, :] - a[None]  # [M, S, 2]
        t = np.clip((rel * v).sum(-1) / (v * v).sum(-1), 0.0, 1.0)
        d_street = np.hypot(*(rel - t[..., None] * v).transpose(2, 0, 1)) - w
        d_node = np.hypot(*(xy[:, None, :] - self.nodes[None]).transpose(2, 0, 1)) - self.node_clear
        return np.minimum(d_street.min(axis=1), d_node.min(axis=1))

    # -- scenery --------------------------------------------------------------
    def _builder(self) -> _Builder:
        return _Builder(self)

    def _dress_side(self, rng: np.random.Generator, k: int, side: float) -> None:
        """Buildings, frontage, trees, lights and parking along one side of a street."""
        s = self.streets[k]
        clear_a, clear_b = self.node_clear[self.links[k][0]], self.node_clear[self.links[k][1]]
        t0, t1 = clear_a + 1.0, s.length - clear_b - 1.0
        if t1 - t0 < 5:
            return
        kerb = s.half_width
        back = s.half_width + s.sidewalk  # the back of the sidewalk
        yaw = s.yaw
        # The street's character: every side draws its own.
        style = rng.choice(
            ["downtown", "residential", "industrial", "park", "mixed"],
            p=[0.25, 0.3, 0.15, 0.1, 0.2],
        )
        hmin, hmax = {
            "downtown": (12, 40),
            "residential": (5, 12),
            "industrial": (6, 14),
            "park": (3, 6),
            "mixed": (5, 22),
        }[style]
        density = {
            "downtown": 1.0,
            "residential": 0.85,
            "industrial": 0.75,
            "park": 0.25,
            "mixed": 0.85,
        }[style] * rng.uniform(0.8, 1.0)
        setback = {
            "downtown": (0.3, 1.0),
            "residential": (1.0, 4.5),
            "industrial": (2.0, 8.0),
            "park": (5.0, 15.0),
            "mixed": (0.5, 5.0),
        }[style]
        setback = rng.uniform(*setback)
        frontage = rng.choice(
            ["none", "wall", "fence", "hedge"],
            p=[0.3, 0.25, 0.2, 0.25] if style != "downtown" else [0.8, 0.2, 0, 0],
        )
        tree_gap = (
            rng.uniform(6, 14)
            if rng.random() < {"park": 0.95, "residential": 0.7}.get(style, 0.35)
            else 0.0
        )
        light_gap = rng.uniform(18, 40)
        parking = rng.uniform(0.3, 0.9) if s.half_width >= 5.0 and rng.random() < 0.7 else 0.0
        sidewalk_refl = rng.uniform(0.3, 0.45)

        b = self._builder()
        mid = s.a + s.dir * (t0 + t1) / 2 + s.left * side * (kerb + s.sidewalk / 2)
        # The raised sidewalk (kerb 12-15 cm).
        b.box(mid, t1 - t0, s.sidewalk, yaw, 0.0, rng.uniform(0.12, 0.16), Material(sidewalk_refl))

        # Building lots, one after the other along the street.
        t = t0 + rng.uniform(0, 6)
        while t < t1 - 6:
            width = min(rng.uniform(8, 28), t1 - t)
            if width < 6:
                break
            if rng.random() < density:
                depth = rng.uniform(8, 24)
                off = back + setback + rng.uniform(0, 1.0) + depth / 2
                centre = s.a + s.dir * (t + width / 2) + s.left * side * off
                height = rng.uniform(hmin, hmax)
                turn = rng.normal(0, 0.03) if rng.random() < 0.3 else 0.0
                self._building(
                    rng,
                    b,
                    centre,
                    width - rng.uniform(0.5, 3),
                    depth,
                    yaw + turn,
                    height,
                    style,
                    s.left * side,
                )
            # Yard and verge plants: bushes in front, trees where no house stands.
            yard = max(setback, 0.0) + (0.0 if self._last_built else 12.0)
            if style != "downtown" and yard > 1.5:
                for _ in range(rng.integers(0, 4)):
                    c = (
                        s.a
                        + s.dir * (t + rng.uniform(0, width))
                        + s.left * side * (back + rng.uniform(0.8, yard))
                    )
                    if self.road_clearance(c[None])[0] > 0.5:
                        if self._last_built or rng.random() < 0.6:
                            b.ellipsoid(
                                c,
                                rng.uniform(0.6, 1.6),
                                0.4,
                                rng.uniform(0.5, 1.2),
                                Material(rng.uniform(0.3, 0.45)),
                                rng.uniform(0.6, 0.9),
                            )
                        else:
                            _tree(rng, b, c, rng.uniform(0.6, 1.3))
            self._last_built = False
            t += width
        # Frontage along the back of the sidewalk (a gap for each gate or drive).
        if frontage != "none":
            h = {
                "wall": rng.uniform(1.0, 2.6),
                "fence": rng.uniform(1.2, 2.2),
                "hedge": rng.uniform(0.9, 1.8),
            }[frontage]
            mat = {
                "wall": Material(rng.uniform(0.15, 0.5)),
                "fence": Material(0.35, 0.2),
                "hedge": Material(rng.uniform(0.3, 0.45)),
            }[frontage]
            see = {"wall": 1.0, "fence": rng.uniform(0.25, 0.6), "hedge": rng.uniform(0.6, 0.85)}[
                frontage
            ]
            thick = {"wall": 0.3, "fence": 0.06, "hedge": 0.8}[frontage]
            t = t0
            while t < t1 - 2:
                run = min(rng.uniform(6, 30), t1 - t)
                c = s.a + s.dir * (t + run / 2) + s.left * side * (back + thick / 2 + 0.2)
                if self._occupied.free(c, run / 2, thick / 2, yaw):
                    b.box(c, run, thick, yaw, 0.0, h, mat, see)
                t += run + rng.uniform(2.5, 5)
        # Trees on the sidewalk (some of them change between sessions).
        if tree_gap > 0:
            t = t0 + rng.uniform(0, tree_gap)
            kind = rng.uniform(0.6, 1.4)  # one species per street
            while t < t1:
                c = s.a + s.dir * t + s.left * side * (kerb + min(1.0, s.sidewalk / 2))
                tb = self._builder()
                _tree(rng, tb, c, kind)
                if rng.random() < 0.15:
                    self._changeable.append((0.5, tb.prims))
                else:
                    b.prims.extend(tb.prims)
                t += tree_gap * rng.uniform(0.8, 1.2)
        # Street lights at the kerb, all of one design along the street.
        t = t0 + rng.uniform(0, light_gap)
        pole_h, arm = rng.uniform(5.5, 9.5), rng.uniform(0.8, 2.5)
        while t < t1:
            c = s.a + s.dir * t + s.left * side * (kerb + 0.4)
            b.cylinder(c, rng.uniform(0.08, 0.14), 0.0, pole_h, Material(0.5))
            head = c - s.left * side * arm / 2
            b.box(head, 0.25, arm, yaw, pole_h - 0.25, pole_h, Material(0.55))
            t += light_gap
        # Bins, benches, bollards, small signs: changeable.
        for _ in range(rng.poisson((t1 - t0) / 25)):
            tt = rng.uniform(t0, t1)
            c = s.a + s.dir * tt + s.left * side * (kerb + rng.uniform(0.4, s.sidewalk - 0.3))
            sb = self._builder()
            _small_object(rng, sb, c, yaw)
            self._changeable.append((0.6, sb.prims))
        # Parking spots along the kerb, inside the road.
        if parking > 0:
            t = t0 + rng.uniform(0, 3)
            while t < t1 - 5:
                c = s.a + s.dir * (t + 2.5) + s.left * side * (kerb - 1.15)
                self._parking.append((c, yaw, parking))
                t += rng.uniform(5.8, 7.0)
        self.static.extend(b.prims)

    def _building(
        self,
        rng: np.random.Generator,
        b: _Builder,
        centre: np.ndarray,
        width: float,
        depth: float,
        yaw: float,
        height: float,
        style: str,
        outward: np.ndarray,
    ) -> None:
        if not self._site_free(centre, width / 2, depth / 2, yaw):
            return
        self._occupied.mark(centre, width / 2, depth / 2, yaw)
        self._last_built = True
        glass = {"downtown": 0.25, "industrial": 0.02}.get(style, 0.08) * rng.uniform(0.5, 1.5)
        mat = Material(rng.uniform(0.12, 0.6), glass)
        b.box(centre, width, depth, yaw, 0.0, height, mat)
        c, s = np.cos(yaw), np.sin(yaw)
        along = np.array([c, s])
        # A wing behind (L-shaped footprint), a setback top floor, a roof box.
        if rng.random() < 0.45:
            ww, wd = width * rng.uniform(0.3, 0.7), depth * rng.uniform(0.5, 1.2)
            wc = (
                centre
                + outward * (depth / 2 + wd / 2 - 0.5)
                + along * rng.choice([-1, 1]) * (width - ww) / 2
            )
            if self._site_free(wc, ww / 2, wd / 2, yaw):
                self._occupied.mark(wc, ww / 2, wd / 2, yaw)
                b.box(wc, ww, wd, yaw, 0.0, height * rng.uniform(0.4, 1.3), mat)
        if height > 10 and rng.random() < 0.4:
            b.box(
                centre + outward * rng.uniform(0, 2),
                width * 0.8,
                depth * 0.7,
                yaw,
                height,
                height + rng.uniform(3, 8),
                mat,
            )
        if rng.random() < 0.3:
            b.box(
                centre,
                rng.uniform(2, 5),
                rng.uniform(2, 5),
                yaw + rng.uniform(0, 1.5),
                height,
                height + rng.uniform(1.5, 3.5),
                Material(0.3),
            )
        # Street-facing features: columns or a canopy at the ground floor.
        if style in ("downtown", "mixed") and rng.random() < 0.4:
            front = centre + outward * (-depth / 2 - 1.5)
            n = int(width // 4)
            for k in range(n):
                pc = front + along * (k - (n - 1) / 2) * 4.0
                b.cylinder(pc, 0.25, 0.0, 4.0, mat)
            b.box(front, width, 3.0, yaw, 4.0, 4.6, mat)

    def _dress_junction(self, rng: np.random.Generator, n: int) -> None:
        """Traffic signs, lights and a signal pole or two at the corners."""
        b = self._builder()
        node = self.nodes[n]
        r = self.node_clear[n] - 0.8
        for ang in rng.uniform(0, 2 * np.pi, rng.integers(1, 4)):
            c = node + r * np.array([np.cos(ang), np.sin(ang)])
            if self.road_clearance(c[None])[0] > -0.3 and not self._on_road(c):
                b.cylinder(c, 0.06, 0.0, 2.6, Material(0.45))
                b.box(c, 0.7, 0.05, ang + np.pi / 2, 2.0, 2.6, Material(0.95))
        if rng.random() < 0.5:
            ang = rng.uniform(0, 2 * np.pi)
            c = node + r * np.array([np.cos(ang), np.sin(ang)])
            if not self._on_road(c):
                b.cylinder(c, 0.12, 0.0, 5.5, Material(0.4))
                b.box(
                    c - 2 * np.array([np.cos(ang), np.sin(ang)]),
                    4.0,
                    0.3,
                    ang + np.pi / 2,
                    5.2,
                    5.6,
                    Material(0.4),
                )
        self.static.extend(b.prims)

    def _site_free(self, c: np.ndarray, hx: float, hy: float, yaw: float) -> bool:
        """No building there yet, and the footprint keeps off every road and sidewalk."""
        if not self._occupied.free(c, hx, hy, yaw):
            return False
        u, v = np.meshgrid(np.linspace(-hx, hx, 5), np.linspace(-hy, hy, 5), indexing="ij")
        pts = c + np.stack(
            [np.cos(yaw) * u - np.sin(yaw) * v, np.sin(yaw) * u + np.cos(yaw) * v], axis=-1
        ).reshape(-1, 2)
        return bool(self.road_clearance(pts).min() > 0.2)

    def _on_road(self, c: np.ndarray) -> bool:
        for s in self.streets:
            if _segment_distance(c[None], s.a, s.b)[0] < s.half_width + 0.3:
                return True
        return False

    def _outskirts(self, rng: np.random.Generator) -> None:
        """Trees, bushes, sheds, halls and low mounds in the blocks and around the town."""
        p = self.params
        x0, y0, x1, y1 = self.bounds(margin=p.outskirts_m)
        b = self._builder()
        area = (x1 - x0) * (y1 - y0)
        for _ in range(int(area / 200)):
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            if self.road_clearance(c[None])[0] < 3:
                continue
            u = rng.random()
            if u < 0.6:
                if self._occupied.free(c, 1.5, 1.5, 0.0):
                    _tree(rng, b, c, rng.uniform(0.7, 1.5))
            elif u < 0.75:  # a clump of bushes
                for _ in range(rng.integers(2, 6)):
                    q = c + rng.normal(0, 1.5, 2)
                    b.ellipsoid(
                        q,
                        rng.uniform(0.6, 1.8),
                        0.3,
                        rng.uniform(0.5, 1.3),
                        Material(rng.uniform(0.3, 0.45)),
                        rng.uniform(0.6, 0.9),
                    )
            elif u < 0.9:  # a low mound: the ground is not a perfect plane
                r = rng.uniform(4, 12)
                h = rng.uniform(0.3, 1.2)
                b.ellipsoid(c, r, -0.3 * h, h, Material(_GRASS), 1.0)
            else:
                w, d, yaw = rng.uniform(4, 30), rng.uniform(4, 20), rng.uniform(0, np.pi)
                if self._site_free(c, w / 2, d / 2, yaw):
                    self._occupied.mark(c, w / 2, d / 2, yaw)
                    b.box(c, w, d, yaw, 0.0, rng.uniform(2.5, 12), Material(rng.uniform(0.15, 0.5)))
        self.static.extend(b.prims)

    # -- sessions -------------------------------------------------------------
    def session_world(self, session: int) -> SessionWorld:
        """The static town plus this session's parked cars and changeable things."""
        from disco_cli import _core

        rng = np.random.default_rng([self.seed, 5, int(session)])
        prims = _Prims()
        prims.extend(self.static)
        for prob, things in self._changeable:
            if rng.random() < prob:
                prims.extend(things)
        b = self._builder()
        for c, yaw, occupancy in self._parking:
            if rng.random() < occupancy:
                jitter = rng.uniform(-0.8, 0.8) * np.array([np.cos(yaw), np.sin(yaw)])
                _car(rng, b, c + jitter, yaw + rng.normal(0, 0.03))
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

    def _movers(self, rng: np.random.Generator) -> np.ndarray:
        """This session's traffic and walkers, one row each: street, heading (+-1), start
        (m), speed (m/s), offset right of the heading (m), length, width, height,
        reflectivity, kind (0 car, 1 person), span start, span length."""
        p = self.params
        rows = []
        for k, s in enumerate(self.streets):
            lo = self.node_clear[self.links[k][0]]
            span = s.length - lo - self.node_clear[self.links[k][1]]
            if span < 10:
                continue
            for heading in (1.0, -1.0):
                for _ in range(rng.poisson(span * p.traffic_per_km / 1000)):
                    rows.append(
                        [
                            k,
                            heading,
                            rng.uniform(0, span),
                            rng.uniform(6, 14),
                            rng.uniform(1.5, 2.1),
                            rng.uniform(3.8, 5.2),
                            rng.uniform(1.7, 2.0),
                            rng.uniform(1.4, 2.0),
                            rng.choice([0.08, 0.2, 0.5, 0.8]),
                            0,
                            lo,
                            span,
                        ]
                    )
                for _ in range(rng.poisson(span * p.pedestrians_per_km / 1000)):
                    off = s.half_width + rng.uniform(0.4, max(0.5, s.sidewalk - 0.4))
                    h = rng.uniform(1.5, 1.95)
                    rows.append(
                        [
                            k,
                            rng.choice([1.0, -1.0]),
                            rng.uniform(0, span),
                            rng.uniform(0.8, 1.7),
                            heading * off,
                            0.5,
                            0.5,
                            h,
                            0.35,
                            1,
                            lo,
                            span,
                        ]
                    )
        return np.array(rows, np.float64).reshape(-1, 12)

    def mover_rows(
        self, movers: np.ndarray, t: float, xy: np.ndarray | None, keep_clear_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Primitive rows of the movers at time `t` (cars: body and cabin; people: a
        cylinder); none within `keep_clear_m` of `xy`."""
        k = movers[:, 0].astype(int)
        heading, s0, speed, right = movers[:, 1], movers[:, 2], movers[:, 3], movers[:, 4]
        a = np.array([self.streets[i].a for i in k]).reshape(-1, 2)
        d = np.array([self.streets[i].dir for i in k]).reshape(-1, 2)
        left = np.array([self.streets[i].left for i in k]).reshape(-1, 2)
        along = movers[:, 10] + np.mod(s0 + heading * speed * t, movers[:, 11])
        pos = a + d * along[:, None] - left * (heading * right)[:, None]
        keep = np.ones(len(movers), bool)
        if xy is not None:
            keep = np.hypot(*(pos - np.asarray(xy)[:2]).T) > keep_clear_m
        yaw = np.array([self.streets[i].yaw for i in k])
        g = self.ground_z(pos[:, 0], pos[:, 1])
        length, width, height = movers[:, 5], movers[:, 6], movers[:, 7]
        rows, refl, drop = [], [], []
        for i in np.flatnonzero(keep):
            x, y = pos[i]
            if movers[i, 9] == 0:  # a car: body, then a narrower cabin of glass
                body = 0.55 * height[i]
                rows.append(
                    [
                        BOX,
                        x,
                        y,
                        g[i] + (0.25 + body) / 2,
                        length[i] / 2,
                        width[i] / 2,
                        (body - 0.25) / 2,
                        yaw[i],
                        1.0,
                    ]
                )
                refl.append(movers[i, 8])
                drop.append(0.03)
                rows.append(
                    [
                        BOX,
                        x,
                        y,
                        g[i] + (body + height[i]) / 2,
                        0.3 * length[i],
                        0.45 * width[i],
                        (height[i] - body) / 2,
                        yaw[i],
                        1.0,
                    ]
                )
                refl.append(0.1)
                drop.append(0.4)
            else:  # a person
                rows.append(
                    [CYLINDER, x, y, g[i] + height[i] / 2, 0.25, 0.25, height[i] / 2, 0.0, 1.0]
                )
                refl.append(movers[i, 8])
                drop.append(0.05)
        return (
            np.array(rows, np.float64).reshape(-1, 9),
            np.array(refl, np.float32),
            np.array(drop, np.float32),
        )

    def ground_reflectivity(self, xy: np.ndarray) -> np.ndarray:
        """Intensity of the ground at world points `[M, 2]`: asphalt, markings, grass."""
        if self._texture is None:
            self._texture = self._paint_ground()
        x0, y0, cell, tex = self._texture
        i = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
        j = np.floor((xy[:, 1] - y0) / cell).astype(np.int64)
        inside = (i >= 0) & (i < tex.shape[0]) & (j >= 0) & (j < tex.shape[1])
        out = np.full(len(xy), _GRASS, np.float32)
        out[inside] = tex[i[inside], j[inside]] / 255.0
        return out

    def _paint_ground(self, cell: float = 0.1) -> tuple[float, float, float, np.ndarray]:
        """A 10 cm raster of the ground's reflectivity (uint8, x 255) over the town."""
        x0, y0, x1, y1 = self.bounds(margin=20.0)
        tex = np.full(
            (int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1), round(_GRASS * 255), np.uint8
        )

        def window(
            cx: float, cy: float, rx: float, ry: float
        ) -> tuple[slice, slice, np.ndarray, np.ndarray]:
            i0 = max(0, int((cx - rx - x0) / cell))
            i1 = min(tex.shape[0], int((cx + rx - x0) / cell) + 1)
            j0 = max(0, int((cy - ry - y0) / cell))
            j1 = min(tex.shape[1], int((cy + ry - y0) / cell) + 1)
            gx = x0 + (np.arange(i0, i1) + 0.5) * cell
            gy = y0 + (np.arange(j0, j1) + 0.5) * cell
            return slice(i0, i1), slice(j0, j1), gx[:, None], gy[None, :]

        asphalt, paint = round(0.2 * 255), round(0.75 * 255)
        for n, node in enumerate(self.nodes):
            r = self.node_clear[n] - 1.0
            si, sj, gx, gy = window(node[0], node[1], r, r)
            tex[si, sj][np.hypot(gx - node[0], gy - node[1]) < r] = asphalt
        for s in self.streets:
            mid = (s.a + s.b) / 2
            ext = np.abs(s.dir) * s.length / 2 + np.abs(s.left) * s.half_width
            si, sj, gx, gy = window(mid[0], mid[1], ext[0], ext[1])
            along = (gx - s.a[0]) * s.dir[0] + (gy - s.a[1]) * s.dir[1]
            across = (gx - s.a[0]) * s.left[0] + (gy - s.a[1]) * s.left[1]
            road = (along > 0) & (along < s.length) & (np.abs(across) < s.half_width)
            # Dashed centre line (3 m of 9 m) and solid edge lines, away from junctions.
            open_road = road & (along > s.half_width + 3) & (along < s.length - s.half_width - 3)
            dash = open_road & (np.abs(across) < 0.08) & (np.mod(along, 9.0) < 3.0)
            edge = open_road & (np.abs(np.abs(across) - (s.half_width - 0.35)) < 0.08)
            view = tex[si, sj]
            view[road] = asphalt
            view[dash | edge] = paint
        return x0, y0, cell, tex

    def describe(self) -> dict:
        return {
            "seed": self.seed,
            "params": self.params.to_dict(),
            "ground_plane": list(self.ground),
            "junctions": len(self.nodes),
            "streets": len(self.streets),
            "static_primitives": len(self.static.rows),
            "changeable_groups": len(self._changeable),
            "parking_spots": len(self._parking),
        }


class _Builder:
    """Adds primitives standing on the town's ground."""

    def __init__(self, town: Town):
        self.town = town
        self.prims = _Prims()

    def _add(self, row: list[float], mat: Material) -> None:
        self.prims.rows.append([float(v) for v in row])
        self.prims.refl.append(float(mat.reflectivity))
        self.prims.drop.append(float(mat.dropout))

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


def _tree(rng: np.random.Generator, b: _Builder, c: np.ndarray, size: float) -> None:
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


def _car(rng: np.random.Generator, b: _Builder, c: np.ndarray, yaw: float) -> None:
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


def _small_object(rng: np.random.Generator, b: _Builder, c: np.ndarray, yaw: float) -> None:
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


class _Occupancy:
    """A 1 m raster of where buildings already stand (no two overlap)."""

    def __init__(self, bounds: tuple[float, float, float, float], cell: float = 1.0):
        self.x0, self.y0, x1, y1 = bounds
        self.cell = cell
        self.grid = np.zeros((int((x1 - self.x0) / cell) + 1, int((y1 - self.y0) / cell) + 1), bool)

    def _cells(self, c: np.ndarray, hx: float, hy: float, yaw: float) -> tuple[np.ndarray, ...]:
        u = np.arange(-hx, hx + self.cell / 2, self.cell / 2)
        v = np.arange(-hy, hy + self.cell / 2, self.cell / 2)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        x = c[0] + np.cos(yaw) * uu - np.sin(yaw) * vv
        y = c[1] + np.sin(yaw) * uu + np.cos(yaw) * vv
        i = np.clip(((x - self.x0) / self.cell).astype(int), 0, self.grid.shape[0] - 1)
        j = np.clip(((y - self.y0) / self.cell).astype(int), 0, self.grid.shape[1] - 1)
        return i.ravel(), j.ravel()

    def free(self, c: np.ndarray, hx: float, hy: float, yaw: float) -> bool:
        return not self.grid[self._cells(c, hx, hy, yaw)].any()

    def mark(self, c: np.ndarray, hx: float, hy: float, yaw: float) -> None:
        self.grid[self._cells(c, hx, hy, yaw)] = True


def _segment_distance(xy: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    v = b - a
    t = np.clip(((xy - a) @ v) / (v @ v), 0.0, 1.0)
    return np.hypot(*(xy - (a + t[:, None] * v)).T)


def _connected(n: int, links: list[tuple[int, int]]) -> bool:
    adj: list[list[int]] = [[] for _ in range(n)]
    for u, v in links:
        adj[u].append(v)
        adj[v].append(u)
    seen, stack = {0}, [0]
    while stack:
        for w in adj[stack.pop()]:
            if w not in seen:
                seen.add(w)
                stack.append(w)
    return len(seen) == n


def wall_world(distance: float, height: float = 10.0, length: float = 40.0) -> SessionWorld:
    """A flat ground and one wall facing the origin at x = `distance` (for tests)."""
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
