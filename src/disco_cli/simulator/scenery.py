"""The town's scenery: buildings, frontage, trees, lights and parking along the streets.

Every street side draws its own character (building heights, setbacks, walls or
fences or hedges, tree rows, street lights, parking), so that no two streets look
alike; junctions get signs and signal poles; trees, bushes, sheds, halls and low
mounds fill the blocks and the land around the town.
"""

from __future__ import annotations

import numpy as np

from disco_cli.simulator.layout import CROWN, CROWN_STEPS, GRASS, Layout, segment_distance
from disco_cli.simulator.objects import Builder, Material, Prims, small_object, tree
from disco_cli.simulator.styles import (
    DENSITY,
    DEPTH,
    FRONTAGE,
    HEIGHTS,
    LOT_WIDTH,
    OUTSKIRTS,
    SETBACK,
    SIDE_STYLES,
    TREE_ROW,
)


class Occupancy:
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


class Scenery(Layout):
    """What stands along the streets (a part of `Town`)."""

    static: Prims
    _changeable: list[tuple[float, Prims]]
    _parking: list[tuple[np.ndarray, float, float]]
    _occupied: Occupancy
    _last_built: bool
    _latent: list[Prims]  # objects that no session has until the change model adds them

    def _builder(self) -> Builder:
        return Builder(self)

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
        town_style = self.params.style
        # Random draws beyond the grid town's own come from this generator, so that the
        # grid town (the default) stays what it always was.
        extra = np.random.default_rng([self.seed, 25, k, int(side > 0)])
        # The street's character: every side draws its own.
        names, weights = SIDE_STYLES[town_style]
        style = rng.choice(names, p=weights)
        hmin, hmax = HEIGHTS[style]
        density = DENSITY[style] * rng.uniform(0.8, 1.0)
        setback = rng.uniform(*SETBACK[style])
        frontage = rng.choice(["none", "wall", "fence", "hedge"], p=FRONTAGE[style])
        tree_gap = rng.uniform(6, 14) if rng.random() < TREE_ROW.get(style, 0.35) else 0.0
        if style == "parkroad":  # an avenue: close-set trees
            tree_gap = extra.uniform(5.0, 8.0)
        light_gap = rng.uniform(18, 40)
        parking = rng.uniform(0.3, 0.9) if s.half_width >= 5.0 and rng.random() < 0.7 else 0.0
        street_height = 0.0
        if style == "terrace":  # one height per street; cars parked along both kerbs
            street_height = extra.uniform(hmin, hmax)
            parking = extra.uniform(0.75, 0.95) if s.half_width >= 4.0 else 0.0
        sidewalk_refl = rng.uniform(0.3, 0.45)
        if style == "boulevard":  # both sides of the street draw one character
            street_height, setback, frontage, tree_gap, light_gap, parking = _boulevard(
                np.random.default_rng([self.seed, 29, k]), s.half_width
            )

        b = self._builder()
        mid = s.a + s.dir * (t0 + t1) / 2 + s.left * side * (kerb + s.sidewalk / 2)
        # The raised sidewalk (kerb 12-15 cm; 18-24 cm on varied terrain).
        kerb_h = rng.uniform(0.12, 0.16) * (1.5 if self.params.terrain == "varied" else 1.0)
        b.box(mid, t1 - t0, s.sidewalk, yaw, 0.0, kerb_h, Material(sidewalk_refl))
        if style == "lot":
            setback = max(setback, self._parking_lot(extra, b, k, side, t0, t1) - back)

        # Building lots, one after the other along the street.
        t = t0 + rng.uniform(0, 6)
        while t < t1 - 6:
            lots = LOT_WIDTH.get(style, (8, 28))
            width = min(rng.uniform(*lots), t1 - t)
            if width < min(6, lots[0]):
                break
            if rng.random() < density:
                depth = rng.uniform(*DEPTH.get(style, (8, 24)))
                off = back + setback + rng.uniform(0, 1.0) + depth / 2
                centre = s.a + s.dir * (t + width / 2) + s.left * side * off
                height = rng.uniform(hmin, hmax)
                turn = rng.normal(0, 0.03) if rng.random() < 0.3 else 0.0
                house = width - rng.uniform(0.5, 3)
                if style == "terrace":  # houses in one line, of one height, a passage apart
                    height = street_height + extra.uniform(-0.4, 0.4)
                    turn, house = 0.0, width - 0.3
                    off = back + setback + depth / 2
                    centre = s.a + s.dir * (t + width / 2) + s.left * side * off
                if style == "boulevard":  # a plain box in line with the street
                    height = street_height + extra.uniform(-1.0, 1.0)
                    self._plain_building(b, centre, width - 2.0, depth, yaw, height)
                    t += width
                    continue
                if style == "suburban":  # a detached house, with garden on either side
                    house = width * extra.uniform(0.45, 0.65)
                    centre = centre + s.dir * extra.uniform(-0.5, 0.5) * (width - house - 2.0)
                self._building(
                    rng, b, centre, house, depth, yaw + turn, height, style, s.left * side
                )
                if style == "hall" and self._last_built:
                    self._containers(extra, b, centre, depth, yaw, s.left * side, width)
            # Yard and verge plants: bushes in front, trees where no house stands.
            yard = max(setback, 0.0) + (0.0 if self._last_built else 12.0)
            if style not in ("downtown", "boulevard") and yard > 1.5:
                plants = rng.integers(0, 4)
                if style in ("suburban", "parkroad"):  # gardens
                    plants += extra.integers(1, 4)
                for _ in range(plants):
                    c = (
                        s.a
                        + s.dir * (t + rng.uniform(0, width))
                        + s.left * side * (back + rng.uniform(0.8, yard))
                    )
                    if self.road_clearance(c[None])[0] > 0.5 and (
                        town_style == "grid" or self._occupied.free(c, 0.8, 0.8, 0.0)
                    ):
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
                            m = b.mark()
                            tree(rng, b, c, rng.uniform(0.6, 1.3))
                            b.tag(m, "trees")
            self._last_built = False
            t += width
        # Frontage along the back of the sidewalk (a gap for each gate or drive).
        if frontage != "none":
            self._frontage(rng, b, k, side, frontage, t0, t1)
        elif self.params.change is not None and style != "downtown":
            # Where none stands, the change model may put up a hedge or a fence.
            lb = self._builder()
            self._frontage(extra, lb, k, side, str(extra.choice(["fence", "hedge"])), t0, t1)
            self._latent.append(lb.prims)
        # Trees on the sidewalk (some of them change between sessions).
        if tree_gap > 0:
            t = t0 + rng.uniform(0, tree_gap)
            kind = rng.uniform(0.6, 1.4)  # one species per street
            while t < t1:
                c = s.a + s.dir * t + s.left * side * (kerb + min(1.0, s.sidewalk / 2))
                tb = self._builder()
                tree(rng, tb, c, kind)
                tb.tag(0, "trees")
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
        furniture = rng.poisson((t1 - t0) / 25) if style != "boulevard" else 0
        if style == "parkroad":  # benches and bins along the park
            furniture += extra.poisson((t1 - t0) / 25)
        for _ in range(furniture):
            tt = rng.uniform(t0, t1)
            c = s.a + s.dir * tt + s.left * side * (kerb + rng.uniform(0.4, s.sidewalk - 0.3))
            sb = self._builder()
            small_object(rng, sb, c, yaw)
            sb.tag(0, "furniture")
            self._changeable.append((0.6, sb.prims))
        # Parking spots along the kerb, inside the road.
        if parking > 0:
            t = t0 + rng.uniform(0, 3)
            while t < t1 - 5:
                c = s.a + s.dir * (t + 2.5) + s.left * side * (kerb - 1.15)
                self._parking.append((c, yaw, parking))
                t += rng.uniform(5.8, 7.0)
        self.static.extend(b.prims)

    def _frontage(
        self,
        rng: np.random.Generator,
        b: Builder,
        k: int,
        side: float,
        kind: str,
        t0: float,
        t1: float,
    ) -> None:
        """A wall, fence or hedge along the back of the sidewalk, with gaps for gates."""
        s = self.streets[k]
        back = s.half_width + s.sidewalk
        # Every value is drawn, whichever is used: the draws stay in step.
        h = {
            "wall": rng.uniform(1.0, 2.6),
            "fence": rng.uniform(1.2, 2.2),
            "hedge": rng.uniform(0.9, 1.8),
        }[kind]
        mat = {
            "wall": Material(rng.uniform(0.15, 0.5)),
            "fence": Material(0.35, 0.2),
            "hedge": Material(rng.uniform(0.3, 0.45)),
        }[kind]
        see = {"wall": 1.0, "fence": rng.uniform(0.25, 0.6), "hedge": rng.uniform(0.6, 0.85)}[kind]
        thick = {"wall": 0.3, "fence": 0.06, "hedge": 0.8}[kind]
        t = t0
        while t < t1 - 2:
            run = min(rng.uniform(6, 30), t1 - t)
            c = s.a + s.dir * (t + run / 2) + s.left * side * (back + thick / 2 + 0.2)
            if self._occupied.free(c, run / 2, thick / 2, s.yaw):
                m = b.mark()
                b.box(c, run, thick, s.yaw, 0.0, h, mat, see)
                if kind != "wall":
                    b.tag(m, kind + "s")
                elif self.params.style == "boulevard":  # its walls change as fences do
                    b.tag(m, "fences")
            t += run + rng.uniform(2.5, 5)

    def _parking_lot(
        self, rng: np.random.Generator, b: Builder, k: int, side: float, t0: float, t1: float
    ) -> float:
        """Two rows of spots square to the street behind its sidewalk, an aisle between,
        and lights; returns how far from the centre line the lot reaches (m)."""
        s = self.streets[k]
        back = s.half_width + s.sidewalk
        occupancy = rng.uniform(0.5, 0.95)
        rows = (back + 1.0 + 2.5, back + 1.0 + 5.0 + 6.5 + 2.5)  # row centres, 6.5 m aisle
        outward = s.left * side
        t = t0 + 1.5
        while t < t1 - 1.5:
            for depth in rows:
                c = s.a + s.dir * t + outward * depth
                if self._occupied.free(c, 1.2, 2.5, s.yaw) and self.road_clearance(c[None])[0] > 0:
                    self._parking.append((c, s.yaw + np.pi / 2, occupancy))
                    self._occupied.mark(c, 1.2, 2.5, s.yaw)
            t += 2.6
        t = t0 + rng.uniform(2, 10)
        while t < t1:
            c = s.a + s.dir * t + outward * (back + 1.0 + 5.0 + 3.25)
            if self.road_clearance(c[None])[0] > 0:
                b.cylinder(c, 0.1, 0.0, 8.0, Material(0.5))
                b.box(c, 0.6, 1.2, s.yaw, 7.8, 8.0, Material(0.55))
            t += rng.uniform(20, 30)
        return rows[1] + 3.5

    def _containers(
        self,
        rng: np.random.Generator,
        b: Builder,
        centre: np.ndarray,
        depth: float,
        yaw: float,
        outward: np.ndarray,
        lot: float,
    ) -> None:
        """A stack or two of shipping containers in the yard beside a hall."""
        along = np.array([np.cos(yaw), np.sin(yaw)])
        for _ in range(rng.integers(0, 3)):
            c = centre + along * rng.uniform(-lot / 2, lot / 2) + outward * (depth / 2 + 4.0)
            turn = yaw + rng.choice([0.0, np.pi / 2])
            if not self._site_free(c, 3.1, 1.3, turn):
                continue
            self._occupied.mark(c, 3.1, 1.3, turn)
            m = b.mark()
            for level in range(rng.integers(1, 4)):
                mat = Material(rng.uniform(0.15, 0.7))
                b.box(c, 6.06, 2.44, turn, 2.6 * level, 2.6 * (level + 1), mat)
            b.tag(m, "buildings")

    def _plain_building(
        self,
        b: Builder,
        centre: np.ndarray,
        width: float,
        depth: float,
        yaw: float,
        height: float,
    ) -> None:
        """One box, no wing, roof box or canopy: nothing that tells one building from
        the next (the boulevard's)."""
        if not self._site_free(centre, width / 2, depth / 2, yaw):
            return
        self._occupied.mark(centre, width / 2, depth / 2, yaw)
        self._last_built = True
        m = b.mark()
        b.box(centre, width, depth, yaw, 0.0, height, Material(0.35, 0.08))
        b.tag(m, "buildings")

    def _building(
        self,
        rng: np.random.Generator,
        b: Builder,
        centre: np.ndarray,
        width: float,
        depth: float,
        yaw: float,
        height: float,
        style: str,
        outward: np.ndarray,
    ) -> None:
        # Row houses stand 0.3 m apart: a narrower footprint keeps the 1 m occupancy
        # raster from seeing each house's neighbour where it stands.
        hx = width / 2 - (0.8 if style == "terrace" else 0.0)
        if not self._site_free(centre, hx, depth / 2, yaw):
            return
        self._occupied.mark(centre, hx, depth / 2, yaw)
        self._last_built = True
        first = b.mark()
        glass = {"downtown": 0.25, "industrial": 0.02, "hall": 0.02}.get(style, 0.08) * rng.uniform(
            0.5, 1.5
        )
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
        b.tag(first, "buildings")

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
            if segment_distance(c[None], s.a, s.b)[0] < s.half_width + 0.3:
                return True
        return False

    def _outskirts(self, rng: np.random.Generator) -> None:
        """Trees, bushes, sheds, halls and low mounds in the blocks and around the town."""
        p = self.params
        x0, y0, x1, y1 = self.bounds(margin=p.outskirts_m)
        b = self._builder()
        area = (x1 - x0) * (y1 - y0)
        m2_each, (u_tree, u_bush, u_mound), size = OUTSKIRTS[p.style]
        grid = p.style == "grid"
        for _ in range(int(area / m2_each)):
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            if self.road_clearance(c[None])[0] < 3:
                continue
            u = rng.random()
            if u < u_tree:
                if self._occupied.free(c, 1.5, 1.5, 0.0):
                    m = b.mark()
                    tree(rng, b, c, rng.uniform(0.7, 1.5))
                    b.tag(m, "trees")
            elif u < u_bush:  # a clump of bushes
                free = grid or self._occupied.free(c, 2.0, 2.0, 0.0)
                for _ in range(rng.integers(2, 6)):
                    q = c + rng.normal(0, 1.5, 2)
                    args = (rng.uniform(0.6, 1.8), 0.3, rng.uniform(0.5, 1.3))
                    mat, prob = Material(rng.uniform(0.3, 0.45)), rng.uniform(0.6, 0.9)
                    if free:
                        b.ellipsoid(q, *args, mat, prob)
            elif u < u_mound:  # a low mound: the ground is not a perfect plane
                r = rng.uniform(4, 12)
                h = rng.uniform(0.3, 1.2)
                if grid or self._occupied.free(c, r / 2, r / 2, 0.0):
                    b.ellipsoid(c, r, -0.3 * h, h, Material(GRASS), 1.0)
            else:
                (w0, w1), (d0, d1), (h0, h1) = size
                w, d, yaw = rng.uniform(w0, w1), rng.uniform(d0, d1), rng.uniform(0, np.pi)
                if self._site_free(c, w / 2, d / 2, yaw):
                    self._occupied.mark(c, w / 2, d / 2, yaw)
                    m = b.mark()
                    b.box(c, w, d, yaw, 0.0, rng.uniform(h0, h1), Material(rng.uniform(0.15, 0.5)))
                    b.tag(m, "buildings")
        if p.terrain == "varied":
            self._hills(np.random.default_rng([self.seed, 27]), b)
        self.static.extend(b.prims)

    def _hills(self, rng: np.random.Generator, b: Builder) -> None:
        """Broad hills and embankments off the roads (varied terrain)."""
        x0, y0, x1, y1 = self.bounds(margin=self.params.outskirts_m)
        for _ in range(int((x1 - x0) * (y1 - y0) / 3000)):
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
            r, h = rng.uniform(10, 30), rng.uniform(1.0, 4.0)
            if self.road_clearance(c[None])[0] > 0.8 * r:
                b.ellipsoid(c, r, -0.2 * h, h, Material(GRASS), 1.0)

    def _crown_roads(self, b: Builder) -> None:
        """Crowned roads (varied terrain): each street rises towards its centre line in
        three thin steps, 2 % of its half width in all (see `Layout.surface_z`)."""
        for k, s in enumerate(self.streets):
            lo = self.node_clear[self.links[k][0]] - 1.0
            length = s.length - lo - (self.node_clear[self.links[k][1]] - 1.0)
            if length <= 0:
                continue
            mid = s.a + s.dir * (lo + length / 2)
            for step in range(1, CROWN_STEPS + 1):
                half = s.half_width * (1.0 - step / (CROWN_STEPS + 1))
                rise = CROWN * s.half_width * step / CROWN_STEPS
                b.box(mid, length, 2 * half, s.yaw, 0.0, rise, Material(0.2))


def _boulevard(rng: np.random.Generator, half_width: float) -> tuple:
    """One boulevard street's character, for both its sides: (building height, setback,
    frontage, tree spacing, light spacing, share of parking spots taken)."""
    height = rng.uniform(8.0, 16.0)
    setback = rng.uniform(4.5, 15.5)
    frontage = str(rng.choice(["wall", "hedge"]))
    tree_gap = rng.uniform(6.0, 10.0)
    light_gap = rng.uniform(20.0, 35.0)
    parking = rng.uniform(0.7, 0.95) if half_width >= 4.0 else 0.0
    return height, setback, frontage, tree_gap, light_gap, parking
