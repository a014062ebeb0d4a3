"""Benchmark: the C++ polar BEV voxelizer against a vectorized NumPy implementation.

Times, in one process, on a ~30k-point scan and a ~120k-point HDL-64 scan (KITTI
frame 0 from ../shared/realdata when present, else a synthetic 64-beam scan):
the C++ voxelizer through `disco_cli.polar_bev` (each SIMD kernel), a vectorized
NumPy implementation of the same binning, and `polar_bev_batch` on 1 and 2 threads.
Prints medians and ratios. Run: `.venv/bin/python benchmarks/bench_voxelizer.py`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import REALDATA, interleaved_medians_ms, print_header

from disco_cli import _core
from disco_cli.model.bev import BEVConfig, polar_bev, polar_bev_batch

KITTI = REALDATA / "kitti00" / "velodyne"


def numpy_bev(points: np.ndarray, config: BEVConfig) -> np.ndarray:
    """Occupancy BEV in vectorized float32 NumPy, tuned (no float64, reciprocals, one flat
    index): the strongest plain-NumPy baseline we could write."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    r = np.sqrt(x * x + y * y)
    keep = (
        (r >= config.min_range) & (r < config.max_range) & (z >= config.z_min) & (z < config.z_max)
    )
    x, y, z, r = x[keep], y[keep], z[keep], r[keep]
    theta = np.arctan2(y, x)
    theta[theta < 0] += np.float32(2 * np.pi)
    ring = np.minimum(
        (r * np.float32(config.rings / config.max_range)).astype(np.int32), config.rings - 1
    )
    sector = np.minimum(
        (theta * np.float32(config.sectors / (2 * np.pi))).astype(np.int32), config.sectors - 1
    )
    scale = np.float32(config.heights / (config.z_max - config.z_min))
    height = np.minimum(
        ((z - np.float32(config.z_min)) * scale).astype(np.int32), config.heights - 1
    )
    out = np.zeros(config.shape, np.float32)
    out.reshape(-1)[(height * config.rings + ring) * config.sectors + sector] = 1.0
    return out


def numpy_bev_float64(points: np.ndarray, config: BEVConfig) -> np.ndarray:
    """The definition as written (docs/bev.md), in float64 NumPy: the plain baseline."""
    p = points[:, :3].astype(np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = np.sqrt(x * x + y * y)
    keep = (
        (r >= config.min_range) & (r < config.max_range) & (z >= config.z_min) & (z < config.z_max)
    )
    x, y, z, r = x[keep], y[keep], z[keep], r[keep]
    theta = np.mod(np.arctan2(y, x), 2 * np.pi)
    ring = np.minimum(np.floor(r / (config.max_range / config.rings)), config.rings - 1)
    sector = np.minimum(np.floor(theta / (2 * np.pi / config.sectors)), config.sectors - 1)
    height_w = (config.z_max - config.z_min) / config.heights
    height = np.minimum(np.floor((z - config.z_min) / height_w), config.heights - 1)
    out = np.zeros(config.shape, np.float32)
    out[height.astype(np.intp), ring.astype(np.intp), sector.astype(np.intp)] = 1.0
    return out


def synthetic_scan(rng: np.random.Generator) -> np.ndarray:
    """A 64-beam, 2000-step scan of a street: ground, two building faces, poles."""
    elev = np.radians(np.linspace(-24.8, 2.0, 64))[:, None]
    azim = np.linspace(-np.pi, np.pi, 2000, endpoint=False)[None, :]
    dx, dy, dz = np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)
    dist = np.full((64, 2000), 120.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = np.where(dz < 0, -1.73 / dz, np.inf)
        walls = np.where(np.abs(dy) > 1e-6, np.where(dy > 0, 9.0, -7.0) / dy, np.inf)
    dist = np.minimum(dist, np.minimum(ground, np.where(walls > 0, walls, np.inf)))
    keep = dist < 100
    pts = np.stack([dx * dist, dy * dist, dz * dist], -1)[keep]
    pts += rng.normal(0, 0.02, pts.shape)
    return np.hstack([pts, rng.uniform(0, 1, (len(pts), 1))]).astype(np.float32)


def load_scans(rng: np.random.Generator) -> tuple[list[np.ndarray], str]:
    files = sorted(KITTI.glob("*.bin")) if KITTI.is_dir() else []
    if files:
        return [
            np.fromfile(f, np.float32).reshape(-1, 4) for f in files
        ], f"KITTI 00 ({len(files)} frames)"
    scans = [synthetic_scan(rng) for _ in range(4)]
    return scans, "synthetic 64-beam scans (../shared/realdata absent)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--repeats", type=int, default=300, help="timed calls on the 30k scan (a third on the full)"
    )
    parser.add_argument("--batch", type=int, default=32, help="scans per batch call")
    args = parser.parse_args()
    print_header("bench_voxelizer")

    rng = np.random.default_rng(0)
    scans, source = load_scans(rng)
    full = scans[0]
    pick = np.sort(rng.choice(len(full), 30_000, replace=False))
    small = np.ascontiguousarray(full[pick])  # a real-looking 30k-point scan, in scan order
    config = BEVConfig()
    # The baseline must compute the same thing, or the comparison means nothing (its
    # float32 binning may differ from the exact definition for a point on an edge).
    for baseline in (numpy_bev, numpy_bev_float64):
        differ = int(np.count_nonzero(baseline(full, config) != polar_bev(full, config)))
        assert differ <= 5, f"{baseline.__name__} and C++ differ in {differ} cells"

    print(f"data: {source}")
    # Rounds of 10 calls of each contender in turn (NumPy included), so all see the
    # same load; NumPy float64 is slow, so the full scan gets a third of the rounds.
    rounds = {"30k": max(3, args.repeats // 10), "full": max(3, args.repeats // 30)}
    print(
        f"grid {config.shape}, mode {config.mode}; medians of {10 * rounds['30k']} calls "
        f"(30k) and {10 * rounds['full']} (full scan) of each, in rounds of 10 calls of "
        "each in turn"
    )
    best = _core._bev_kernel_level()
    kernel_name = _core._bev_kernel_name

    def at_level(level: int, pts: np.ndarray, cfg: BEVConfig = config):
        def run():
            _core._set_bev_kernel_level(level)
            return polar_bev(pts, cfg)

        return run

    for name, pts, n_rounds in (
        ("30k", small, rounds["30k"]),
        (f"{len(full) // 1000}k HDL-64", full, rounds["full"]),
    ):
        contenders = {
            "numpy float64": lambda p=pts: numpy_bev_float64(p, config),
            "numpy tuned": lambda p=pts: numpy_bev(p, config),
        }
        # Every kernel this CPU has, forced in turn, then the other modes on the best.
        for level in range(best, -1, -1):
            contenders[kernel_name(level)] = at_level(level, pts)
        for mode in ("density", "max_height"):
            contenders[mode] = at_level(best, pts, BEVConfig(mode=mode))
        ms = interleaved_medians_ms(contenders, n_rounds, warmup=3)
        _core._set_bev_kernel_level(best)
        numpy_ms, plain_ms = ms["numpy tuned"], ms["numpy float64"]
        print(f"\n{name} points ({len(pts)}), float32 N x 4:")
        print(f"  NumPy float64 (plain)   {plain_ms:8.3f} ms")
        print(f"  NumPy float32 (tuned)   {numpy_ms:8.3f} ms")
        for level in range(best, -1, -1):
            t = ms[kernel_name(level)]
            print(
                f"  C++ {kernel_name(level):<20s}{t:8.3f} ms   {numpy_ms / t:5.1f}x tuned NumPy, "
                f"{plain_ms / t:5.1f}x plain"
            )
        for mode in ("density", "max_height"):
            print(f"  C++ {kernel_name(best)}, {mode:<10s}{ms[mode]:8.3f} ms")

    batch = [scans[i % len(scans)] for i in range(args.batch)]
    reps = max(5, args.repeats // 3)
    # 1 and 2 threads alternate, so both see the same spells of load from other jobs;
    # the minimum is the run that had the cores to itself.
    wall: dict[int, list[float]] = {1: [], 2: []}
    cpu: dict[int, list[float]] = {1: [], 2: []}
    for threads in (1, 2):
        polar_bev_batch(batch, config, threads=threads)  # warm up
    for _ in range(reps):
        for threads in (1, 2):
            c0, t0 = time.process_time_ns(), time.perf_counter_ns()
            polar_bev_batch(batch, config, threads=threads)
            wall[threads].append((time.perf_counter_ns() - t0) / 1e6)
            cpu[threads].append((time.process_time_ns() - c0) / 1e6)
    print(f"\nbatch of {args.batch} full scans, {reps} calls each, alternating:")
    rate = args.batch * 1e3
    for threads in (1, 2):
        med, fastest = float(np.median(wall[threads])), min(wall[threads])
        print(
            f"  {threads} thread{'s' if threads > 1 else ' '}  median {med:7.2f} ms "
            f"({rate / med:5.0f} scans/s), min {fastest:7.2f} ms ({rate / fastest:5.0f} scans/s), "
            f"CPU {float(np.median(cpu[threads])):6.2f} ms"
        )
    speedup_median = np.median(wall[1]) / np.median(wall[2])
    speedup_min = min(wall[1]) / min(wall[2])
    print(f"  2-thread throughput: {speedup_median:4.2f}x (medians), {speedup_min:4.2f}x (minima)")


if __name__ == "__main__":
    main()
