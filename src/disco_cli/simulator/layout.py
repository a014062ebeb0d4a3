"""The town's layout: the street network, the ground plane and the paint on it.

A jittered grid of junctions joined by straight streets; some inner links are
removed (keeping every junction on two or more streets and the network
connected), so blocks differ in size and there are T-junctions and loops.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from disco_cli.errors import DiscoError

if TYPE_CHECKING:
    from disco_cli.simulator.params import TownParams

GRASS = 0.3  # reflectivity of the ground off the roads
CROWN, CROWN_STEPS = 0.02, 3  # crowned roads: 2 % rise over the half width, in steps


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


class Layout:
    """Streets and ground of a town (a part of `Town`)."""

    params: TownParams

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
            if deg.min() < 2 or not connected(len(nodes), kept):
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

    def surface_z(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Height of the surface a car drives on: the ground, or on varied terrain the
        crowned road (three steps up to 2 % of the half width at the centre line)."""
        if self.params.terrain == "flat":
            return self.ground_z(x, y)
        xy = np.stack(np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float)), -1)
        flat = xy.reshape(-1, 2)
        rise = np.zeros(len(flat))
        for k, s in enumerate(self.streets):
            lo = self.node_clear[self.links[k][0]] - 1.0
            hi = s.length - (self.node_clear[self.links[k][1]] - 1.0)
            rel = flat - s.a
            along, across = rel @ s.dir, np.abs(rel @ s.left)
            on = (along >= lo) & (along <= hi)
            for step in range(1, CROWN_STEPS + 1):
                half = s.half_width * (1.0 - step / (CROWN_STEPS + 1))
                up = on & (across <= half)
                rise[up] = np.maximum(rise[up], CROWN * s.half_width * step / CROWN_STEPS)
        return self.ground_z(x, y) + rise.reshape(np.shape(xy)[:-1])

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

    def ground_reflectivity(self, xy: np.ndarray) -> np.ndarray:
        """Intensity of the ground at world points `[M, 2]`: asphalt, markings, grass."""
        if self._texture is None:
            self._texture = self._paint_ground()
        x0, y0, cell, tex = self._texture
        i = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
        j = np.floor((xy[:, 1] - y0) / cell).astype(np.int64)
        inside = (i >= 0) & (i < tex.shape[0]) & (j >= 0) & (j < tex.shape[1])
        out = np.full(len(xy), GRASS, np.float32)
        out[inside] = tex[i[inside], j[inside]] / 255.0
        return out

    def _paint_ground(self, cell: float = 0.1) -> tuple[float, float, float, np.ndarray]:
        """A 10 cm raster of the ground's reflectivity (uint8, x 255) over the town."""
        x0, y0, x1, y1 = self.bounds(margin=20.0)
        tex = np.full(
            (int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1), round(GRASS * 255), np.uint8
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


def segment_distance(xy: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    v = b - a
    t = np.clip(((xy - a) @ v) / (v @ v), 0.0, 1.0)
    return np.hypot(*(xy - (a + t[:, None] * v)).T)


def connected(n: int, links: list[tuple[int, int]]) -> bool:
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
