"""Routes through the town and the sensor poses along them.

Session 0 drives a closed loop that returns to its start. Later sessions revisit
part of an earlier route (odd sessions in the opposite direction, even ones in the
same direction, starting elsewhere) and then drive on into other streets. Each
session keeps its own distance to the right of the road's centre line, so two
passes of one street are 0.6-3 m apart sideways, and starts at its own phase, so
that scan positions never coincide.
"""

from __future__ import annotations

import heapq

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.simulator.world import Town


class RoadGraph:
    def __init__(self, town: Town):
        self.nodes = town.nodes
        self.adj: list[list[int]] = [[] for _ in range(len(town.nodes))]
        for u, v in town.links:
            self.adj[u].append(v)
            self.adj[v].append(u)
        for a in self.adj:
            a.sort()

    def length(self, u: int, v: int) -> float:
        return float(np.hypot(*(self.nodes[v] - self.nodes[u])))

    def distances_to(self, target: int) -> np.ndarray:
        dist = np.full(len(self.nodes), np.inf)
        dist[target] = 0.0
        heap = [(0.0, target)]
        while heap:
            d, u = heapq.heappop(heap)
            if d > dist[u]:
                continue
            for w in self.adj[u]:
                nd = d + self.length(u, w)
                if nd < dist[w]:
                    dist[w] = nd
                    heapq.heappush(heap, (nd, w))
        return dist

    def route_length(self, path: list[int]) -> float:
        return float(sum(self.length(u, v) for u, v in zip(path[:-1], path[1:])))


def loop_route(
    graph: RoadGraph, rng: np.random.Generator, target_m: float, tries: int = 64
) -> list[int]:
    """A closed route (first node = last node) of at most about `target_m` metres.

    Of `tries` random loops, the longest that fits in `target_m` (so that a session
    of that length closes its loop); the shortest one when none fits.
    """
    loops = [_one_loop(graph, rng, target_m) for _ in range(tries)]
    # No U-turn where the loop closes either (out and back along one street).
    loops = [p for p in loops if p[1] != p[-2]] or loops
    lengths = np.array([graph.route_length(p) for p in loops])
    fits = np.flatnonzero(lengths <= target_m)
    best = fits[np.argmax(lengths[fits])] if len(fits) else int(np.argmin(lengths))
    return loops[int(best)]


def _one_loop(graph: RoadGraph, rng: np.random.Generator, target_m: float) -> list[int]:
    """One random closed route of roughly `target_m` metres, no U-turns.

    It explores new streets while the way home still fits in the budget, then turns
    for home along the shortest way that needs no U-turn.
    """
    n = len(graph.nodes)
    start = int(rng.integers(n))
    home = graph.distances_to(start)
    path, used, length = [start], set(), 0.0
    going_home = False
    for _ in range(10 * n + 100):
        cur = path[-1]
        prev = path[-2] if len(path) > 1 else -1
        options = [w for w in graph.adj[cur] if w != prev] or list(graph.adj[cur])
        if len(path) > 2 and cur == start:
            return path
        if not going_home and length + home[cur] >= 0.7 * target_m and len(path) > 3:
            going_home = True
        if going_home:
            nxt = min(options, key=lambda w: (graph.length(cur, w) + home[w], w))
        else:
            fresh = [
                w
                for w in options
                if (min(cur, w), max(cur, w)) not in used
                and length + graph.length(cur, w) + home[w] <= target_m
            ]
            nxt = int(rng.choice(fresh)) if fresh else int(rng.choice(options))
        used.add((min(cur, nxt), max(cur, nxt)))
        length += graph.length(cur, nxt)
        path.append(int(nxt))
    # The greedy way home circled: close the loop by the plain shortest path.
    return path + _shortest_path(graph, path[-1], start)[1:]


def _shortest_path(graph: RoadGraph, a: int, b: int) -> list[int]:
    dist = graph.distances_to(b)
    path = [a]
    while path[-1] != b:
        cur = path[-1]
        path.append(int(min(graph.adj[cur], key=lambda w: graph.length(cur, w) + dist[w])))
    return path


def extend_route(
    graph: RoadGraph,
    rng: np.random.Generator,
    path: list[int],
    target_m: float,
    avoid: set[tuple[int, int]],
) -> list[int]:
    """Drive on from the end of `path` (no U-turns, new streets first) to `target_m`."""
    path = list(path)
    length = graph.route_length(path)
    used = set(avoid)
    while length < target_m:
        cur, prev = path[-1], (path[-2] if len(path) > 1 else -1)
        options = [w for w in graph.adj[cur] if w != prev] or list(graph.adj[cur])
        fresh = [w for w in options if (min(cur, w), max(cur, w)) not in used]
        nxt = int(rng.choice(fresh or options))
        used.add((min(cur, nxt), max(cur, nxt)))
        length += graph.length(cur, nxt)
        path.append(int(nxt))
    return path


def revisit_route(
    graph: RoadGraph, rng: np.random.Generator, base: list[int], target_m: float, reverse: bool
) -> list[int]:
    """Part of the closed route `base` (about half), reversed or not, then new streets."""
    cycle = base[:-1]
    k = len(cycle)
    share = min(target_m * rng.uniform(0.45, 0.65), graph.route_length(base) * 0.8)
    first = int(rng.integers(k))
    part = [cycle[first]]
    while graph.route_length(part) < share and len(part) < k:
        part.append(cycle[(first + len(part)) % k])
    if reverse:
        part = part[::-1]
    links = {(min(u, v), max(u, v)) for u, v in zip(base[:-1], base[1:])}
    return extend_route(graph, rng, part, target_m, links)


def _smooth(points: np.ndarray, window: int, closed: bool) -> np.ndarray:
    kernel = np.ones(window) / window
    pad = window // 2
    if closed:
        ext = np.concatenate([points[-pad:], points, points[:pad]])
    else:
        first, last = np.repeat(points[:1], pad, 0), np.repeat(points[-1:], pad, 0)
        ext = np.concatenate([first, points, last])
    out = np.stack([np.convolve(ext[:, i], kernel, mode="same") for i in range(2)], axis=1)
    return out[pad : pad + len(points)]


def lane_path(
    nodes: np.ndarray,
    path: list[int],
    offset: float,
    closed: bool,
    spacing: float = 0.25,
    smooth_m: float = 12.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth driving line `offset` metres right of the centre line.

    Returns dense points `[M, 2]` and their arc lengths `[M]`.
    """
    pts = nodes[path].astype(np.float64)
    if closed:
        pts = pts[:-1]
    seg = np.diff(np.concatenate([pts, pts[:1]]) if closed else pts, axis=0)
    d = seg / np.linalg.norm(seg, axis=1, keepdims=True)
    right = np.stack([d[:, 1], -d[:, 0]], axis=1)
    # Mitre joins: the offset lines of two streets meet at the corner.
    shifted = np.empty_like(pts)
    for i in range(len(pts)):
        r_out = right[i] if (closed or i < len(right)) else right[-1]
        r_in = right[i - 1] if (closed or i > 0) else right[0]
        m = r_in + r_out
        shifted[i] = pts[i] + offset * m / max(1.0 + r_in @ r_out, 0.2)
    ring = np.concatenate([shifted, shifted[:1]]) if closed else shifted
    dense = [ring[:1]]
    for a, b in zip(ring[:-1], ring[1:]):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / spacing)))
        t = (np.arange(1, n + 1) / n)[:, None]
        dense.append(a + t * (b - a))
    line = np.concatenate(dense)
    if closed:
        line = line[:-1]
    line = _smooth(line, max(3, int(smooth_m / spacing)) | 1, closed)
    step = np.hypot(*np.diff(np.concatenate([line, line[:1]]) if closed else line, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    if closed:
        return np.concatenate([line, line[:1]]), s
    return line, s


def _wiggle(
    rng: np.random.Generator, x: np.ndarray, amplitude: float, periods: tuple[float, float]
) -> np.ndarray:
    """A smooth random function: a few sinusoids of random phase."""
    out = np.zeros_like(x, dtype=np.float64)
    for _ in range(3):
        period = rng.uniform(*periods)
        out += np.sin(2 * np.pi * x / period + rng.uniform(0, 2 * np.pi))
    return amplitude * out / np.sqrt(1.5)


def open_stations(
    rng: np.random.Generator, frames: int, step_m: float, phase: float
) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths of `frames` scans about `step_m` apart (speed +-15 %), and lane drift."""
    k = np.arange(frames)
    steps = step_m * (1.0 + np.clip(_wiggle(rng, k, 0.08, (30, 150)), -0.15, 0.15))
    stations = phase + np.concatenate([[0.0], np.cumsum(steps[:-1])])
    return stations, _wiggle(rng, stations, 0.15, (60, 200))


def loop_stations(
    rng: np.random.Generator, frames: int, step_m: float, lap_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Stations around a closed loop of `lap_m` metres, possibly more than one lap.

    The speed profile repeats every lap, so frame `n` of lap 2 would fall where frame
    `n` of lap 1 was; each new lap starts a little further on (10-25 % of a step)
    and in another part of the lane (0.3-1 m nearer the centre), as a real second
    pass would.
    """
    per_lap = max(1, int(round(lap_m / step_m)))
    base = lap_m / per_lap
    k = np.arange(frames)
    wobble = np.zeros(frames)
    for cycles in (1, 2, 3):  # whole cycles per lap: zero net displacement over a lap
        amp = 0.05 * base * per_lap / (2 * np.pi * cycles)
        wobble += amp * np.sin(2 * np.pi * cycles * k / per_lap + rng.uniform(0, 2 * np.pi))
    lap = k // per_lap
    stations = base * k + wobble + lap * rng.uniform(0.1, 0.25) * base
    lateral = _wiggle(rng, np.mod(stations, lap_m), 0.1, (60, 200)) - lap * rng.uniform(0.3, 1.0)
    return np.mod(stations, lap_m), lateral


def sensor_poses(
    town: Town,
    line: np.ndarray,
    s: np.ndarray,
    closed: bool,
    stations: np.ndarray,
    lateral: np.ndarray,
    mount_height: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Sensor poses `[frames, 4, 4]` at arc lengths `stations` along a driving line.

    `lateral` moves each pose right of the line. The car follows the ground's slope
    with a little pitch and roll of its own; the sensor sits `mount_height` above.
    """
    frames = len(stations)
    if not closed and stations[-1] > s[-1]:
        raise DiscoError("internal: the route is shorter than the frames asked for")
    x = np.interp(stations, s, line[:, 0])
    y = np.interp(stations, s, line[:, 1])
    tangent = np.gradient(line, s, axis=0)
    if closed:  # the ends of a closed line meet: use the wrapped difference there
        tangent[0] = tangent[-1] = line[1] - line[-2]
    heading_dense = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    heading = np.interp(stations, s, heading_dense)
    x += lateral * np.sin(heading)
    y -= lateral * np.cos(heading)
    a, b, _ = town.ground
    fwd = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    # Nose up on a climb (pitch about y is negative then), roll with the side slope.
    pitch = -np.arctan(fwd @ np.array([a, b])) + np.radians(_wiggle(rng, stations, 0.3, (15, 60)))
    roll = np.arctan(left @ np.array([a, b])) + np.radians(_wiggle(rng, stations, 0.3, (15, 60)))
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for i in range(frames):
        R = _rz(heading[i]) @ _ry(pitch[i]) @ _rx(roll[i])
        ground = np.array([x[i], y[i], town.surface_z(x[i], y[i])])
        poses[i, :3, :3] = R
        poses[i, :3, 3] = ground + R @ np.array([0.0, 0.0, mount_height])
    return poses


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
