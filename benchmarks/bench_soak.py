"""Soak: one `LoopDetector` fed a long stream of scans in one process (or, with
`--queries N`, N queries against one map); resident memory and time per scan at
intervals after a warm-up.

    .venv/bin/python benchmarks/bench_soak.py [--scans 20000] [--pool 200] [--every 1000]
    .venv/bin/python benchmarks/bench_soak.py --queries 10000 [--pool 200]

With `--queries`, the pool is written to a map (`Map.add_many`, in a temporary folder)
and then queried round and round with `Map.query` (top 10, the default search: re-ranking,
refined yaw, snap), each query a perturbed pool scan as below. Nothing is kept between
queries by design, so the target is growth under 5 % of the warm-up VmRSS, flat time.

The scans are a pool of `--pool` simulated HDL-32E scans along session 00 of a
generated town (`disco_cli.simulator`), fed round and round, each turned by a random
yaw of up to 5 degrees about the sensor and given 1 cm of fresh Gaussian noise, so
that no two fed scans are equal and every lap revisits the same places (the detector
finds loops and makes `Loop`s all along). Simulating 20,000 distinct scans would
cost more than the soak itself.

The detector runs as `disco loops` does without `--verify` (topk 1, every pair a
candidate, exclusion window 50 frames): `--verify` also estimates every loop's pose,
which keeps each scan's points (12 bytes a point, by design; see loop_detector.py).

Printed at every `--every` scans: VmRSS (from /proc/self/status), its growth since the
end of the warm-up (the first `--warmup` scans), what the detector keeps by design
(one signature and one feature image per scan: the growth that must be there), the
growth beyond that, and the median time per scan over the interval. The target is
growth beyond the kept data under 5 % of the warm-up VmRSS, and a flat time per scan
(the exact search over all earlier signatures does grow with the map, by design).
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import time

import numpy as np
from _common import print_header


def vm_rss_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def simulated_pool(n: int, seed: int) -> list[np.ndarray]:
    """`n` HDL-32E scans along session 00 of a default town, in the sensor frame."""
    from disco_cli.simulator import get_sensor, plan_sessions, scan
    from disco_cli.simulator.world import Town

    sensor = get_sensor("hdl32")
    town = Town(seed)
    plan = plan_sessions(town, sensor, 1, n, 2.0, seed)[0]
    world = town.session_world(0)
    return [scan(world, pose, sensor, seed=i, town=town) for i, pose in enumerate(plan.poses)]


def perturbed(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The scan turned by up to 5 degrees about z, with 1 cm of noise on x, y, z."""
    a = np.radians(rng.uniform(-5.0, 5.0))
    c, s = np.cos(a), np.sin(a)
    out = points.copy()
    x, y = points[:, 0], points[:, 1]
    out[:, 0] = c * x - s * y
    out[:, 1] = s * x + c * y
    out[:, :3] += rng.normal(0.0, 0.01, size=(len(points), 3)).astype(np.float32)
    return out


def kept_bytes(detector) -> int:
    """What the detector keeps by design for the scans added so far: the stored feature
    rows, the signature index and the per-scan times and travel."""
    store = detector._store
    n = store.n
    total = store.nbytes()
    index = detector._index
    if index is not None:
        total += sum(
            v.nbytes * min(1.0, n / max(len(v), 1))  # count the rows in use, not spare room
            for v in vars(index).values()
            if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) >= n
        )
    return int(total + detector._times.nbytes + detector._travelled.nbytes)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=20000, help="scans to feed")
    ap.add_argument("--pool", type=int, default=200, help="distinct simulated scans")
    ap.add_argument("--every", type=int, default=0, help="report interval (default scans/20)")
    ap.add_argument("--warmup", type=int, default=0, help="warm-up scans (default scans/10)")
    ap.add_argument("--model", default="default")
    ap.add_argument("--verify", action="store_true", help="also estimate every loop's pose")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--queries", type=int, default=0, help="soak a query stream instead")
    args = ap.parse_args()
    if args.queries:
        soak_queries(args)
        return
    every = args.every or max(1, args.scans // 20)
    warmup = args.warmup or max(1, args.scans // 10)

    import torch

    from disco_cli.query.loop_detector import LoopDetector

    print_header("bench_soak")
    print(f"torch threads {torch.get_num_threads()}; OMP_NUM_THREADS "
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}")  # fmt: skip
    t0 = time.perf_counter()
    pool = simulated_pool(args.pool, args.seed)
    points = statistics.median(len(p) for p in pool)
    print(f"pool: {len(pool)} simulated scans (median {points:.0f} points) "
          f"in {time.perf_counter() - t0:.1f} s")  # fmt: skip
    detector = LoopDetector(args.model, exclude_frames=50, verify=args.verify, topk=1)
    rng = np.random.default_rng(args.seed)
    print(f"feeding {args.scans} scans, warm-up {warmup}, report every {every}")
    print(f"{'scans':>7} {'VmRSS MB':>9} {'growth':>8} {'kept MB':>8} {'beyond':>8} "
          f"{'ms/scan':>8} {'loops':>6}")  # fmt: skip

    base_rss = base_kept = None
    times: list[float] = []
    interval_ms: list[float] = []
    loops = 0
    for i in range(args.scans):
        scan = perturbed(pool[i % len(pool)], rng)
        start = time.perf_counter()
        found = detector.add(scan)
        times.append(time.perf_counter() - start)
        loops += len(found)
        done = i + 1
        if done == warmup:
            gc.collect()
            base_rss, base_kept = vm_rss_bytes(), kept_bytes(detector)
        if done % every == 0 or done == args.scans:
            rss, kept = vm_rss_bytes(), kept_bytes(detector)
            ms = 1000 * statistics.median(times)
            times.clear()
            if base_rss is None:
                print(f"{done:7d} {rss / 1e6:9.1f} {'(warm-up)':>8} {kept / 1e6:8.1f} "
                      f"{'':>8} {ms:8.2f} {loops:6d}")  # fmt: skip
                continue
            interval_ms.append(ms)
            growth = 100 * (rss - base_rss) / base_rss
            beyond = 100 * ((rss - base_rss) - (kept - base_kept)) / base_rss
            print(f"{done:7d} {rss / 1e6:9.1f} {growth:+7.2f}% {kept / 1e6:8.1f} "
                  f"{beyond:+7.2f}% {ms:8.2f} {loops:6d}")  # fmt: skip
    if base_rss is None or not interval_ms:
        print("too few scans for a figure after the warm-up")
        return
    rss, kept = vm_rss_bytes(), kept_bytes(detector)
    growth = 100 * (rss - base_rss) / base_rss
    beyond = 100 * ((rss - base_rss) - (kept - base_kept)) / base_rss
    drift = interval_ms[-1] / interval_ms[0]
    print(
        f"after {args.scans} scans: VmRSS {base_rss / 1e6:.1f} -> {rss / 1e6:.1f} MB "
        f"({growth:+.2f} %), of which kept by design {(kept - base_kept) / 1e6:.1f} MB; "
        f"beyond it {beyond:+.2f} % (target < 5 %): {'ok' if beyond < 5 else 'OVER'}"
    )
    print(
        f"time per scan: median {interval_ms[0]:.2f} ms in the first interval after the "
        f"warm-up, {interval_ms[-1]:.2f} ms in the last ({drift:.2f}x)"
    )


def soak_queries(args) -> None:
    """`--queries N`: one map, N queries in one process; VmRSS and time per query."""
    import tempfile
    from pathlib import Path

    from disco_cli.maps.facade import Map

    n = args.queries
    every = args.every or max(1, n // 20)
    warmup = args.warmup or max(1, n // 10)
    print_header("bench_soak --queries")
    t0 = time.perf_counter()
    pool = simulated_pool(args.pool, args.seed)
    print(f"pool: {len(pool)} simulated scans in {time.perf_counter() - t0:.1f} s")
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "map.db"
        with Map.create(db, args.model) as m:
            m.add_many((p, f"scan-{i}", None) for i, p in enumerate(pool))
        with Map.open(db) as m:
            print(f"map: {len(m)} scans; {n} queries, warm-up {warmup}, report every {every}")
            print(f"{'queries':>7} {'VmRSS MB':>9} {'growth':>8} {'ms/query':>9}")
            base = None
            times: list[float] = []
            interval_ms: list[float] = []
            for i in range(n):
                query = perturbed(pool[i % len(pool)], rng)
                start = time.perf_counter()
                m.query(query, topk=10)
                times.append(time.perf_counter() - start)
                done = i + 1
                if done == warmup:
                    gc.collect()
                    base = vm_rss_bytes()
                if done % every == 0 or done == n:
                    rss = vm_rss_bytes()
                    ms = 1000 * statistics.median(times)
                    times.clear()
                    if base is None:
                        print(f"{done:7d} {rss / 1e6:9.1f} {'(warm-up)':>8} {ms:9.2f}")
                        continue
                    interval_ms.append(ms)
                    grown = 100 * (rss - base) / base
                    print(f"{done:7d} {rss / 1e6:9.1f} {grown:+7.2f}% {ms:9.2f}")
    if base is None or not interval_ms:
        print("too few queries for a figure after the warm-up")
        return
    growth = 100 * (rss - base) / base
    print(
        f"after {n} queries: VmRSS {base / 1e6:.1f} -> {rss / 1e6:.1f} MB ({growth:+.2f} %, "
        f"target < 5 %): {'ok' if growth < 5 else 'OVER'}; time per query {interval_ms[0]:.2f} "
        f"-> {interval_ms[-1]:.2f} ms ({interval_ms[-1] / interval_ms[0]:.2f}x)"
    )


if __name__ == "__main__":
    main()
