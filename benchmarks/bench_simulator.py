"""Simulator speed: ray casting one HDL-32E scan in a generated town, on one core.

    .venv/bin/python benchmarks/bench_simulator.py [--scans 40] [--seed 0]

1. Ray casting alone (`RaycastWorld.cast_scans`, one thread): median per scan, for
   scans along session 00 of a default town; the baseline, in the same process, is
   the same C++ caster with one grid cell over the whole town, so that every ray
   tests every primitive (what the 2D grid and its DDA walk save).
2. A whole scan on one core: the world at the scan's time (moving cars and people),
   ray casting, noise, dropout and intensity (NumPy), median per scan.
3. `simulate()` end to end with all cores: scans per second, and the time a
   2,000-scan training set would take at that rate.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
from _common import median_of_ms as median_ms
from _common import print_header


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=40, help="scans to time in each part")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from disco_cli import _core
    from disco_cli.simulator import cast, finish_scan, get_sensor, plan_sessions, simulate
    from disco_cli.simulator.world import Town

    print_header("bench_simulator")
    sensor = get_sensor("hdl32")
    town = Town(args.seed)
    plan = plan_sessions(town, sensor, 1, args.scans, 2.0, args.seed)[0]
    world = town.session_world(0)
    dirs = sensor.directions()
    town.ground_reflectivity(np.zeros((1, 2)))  # paint the ground once, outside the timing
    print(
        f"town: {len(town.streets)} streets, {world.caster.size} primitives, "
        f"grid {world.caster.grid_shape}; sensor {sensor.name}: {sensor.rays} rays per scan"
    )

    # 1. Ray casting alone, one thread, against one big cell.
    one_cell = _core.RaycastWorld(world.table, *town.ground, 1e4)
    ts, base, points = [], [], []
    for i in range(args.scans):
        seed = np.array([i], np.uint64)
        t = time.perf_counter()
        r, ids, _ = world.caster.cast_scans(plan.poses[i][None], dirs, sensor.max_range, seed, 1)
        ts.append(time.perf_counter() - t)
        points.append(int((ids != _core.RAYCAST_MISS).sum()))
        if i < max(3, args.scans // 8):  # the baseline is slow: fewer scans
            t = time.perf_counter()
            r2, ids2, _ = one_cell.cast_scans(plan.poses[i][None], dirs, sensor.max_range, seed, 1)
            base.append(time.perf_counter() - t)
            assert np.array_equal(ids, ids2), "grid and brute force disagree"
    cast_ms, base_ms = median_ms(ts), median_ms(base)
    print(
        f"1. ray casting, 1 thread: median {cast_ms:.1f} ms per scan = {1e3 / cast_ms:.1f} "
        f"scans/s ({np.median(points):.0f} returns before dropout); one cell (every ray x "
        f"every primitive): {base_ms:.0f} ms, {base_ms / cast_ms:.0f}x slower"
    )

    # 2. A whole scan on one core.
    ts, sizes = [], []
    for i in range(args.scans):
        t = time.perf_counter()
        w = world.at(i / sensor.rate_hz, plan.poses[i, :2, 3])  # with the moving cars
        r, ids, cosi = cast(w, plan.poses[i], sensor, np.array([i], np.uint64), 1)
        pts = finish_scan(
            np.random.default_rng(i), sensor, dirs, plan.poses[i], r[0], ids[0], cosi[0], w, town
        )
        ts.append(time.perf_counter() - t)
        sizes.append(len(pts))
    full_ms = median_ms(ts)
    print(
        f"2. whole scan, 1 core: median {full_ms:.1f} ms = {1e3 / full_ms:.1f} scans/s "
        f"({np.median(sizes):.0f} points)"
    )

    # 3. End to end, all cores, written to disk.
    n = 2 * args.scans
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        simulate(tmp, sessions=2, frames=args.scans, step_m=2.0, seed=args.seed, threads=0)
        wall = time.perf_counter() - t
    print(
        f"3. simulate(), 2 sessions x {args.scans} scans, all cores: {wall:.1f} s incl. town "
        f"generation = {n / wall:.1f} scans/s; 2,000 scans at this rate: "
        f"{2000 / (n / wall):.0f} s"
    )


if __name__ == "__main__":
    main()
