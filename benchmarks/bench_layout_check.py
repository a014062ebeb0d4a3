"""The headerless .bin scan check (`io/readers/plausible.py`): its time per scan, and
the share of "no return" that real sensors' layouts hold.

Every read of a KITTI, NCLT or Oxford .bin runs `check_layout` on the points, so it sits
on every query's path (issue 41 asks <= 0.2 ms on a 17k-30k point scan). Timed here on
a bundled sample scan (17k points), on a 25,944-point scan with every third point NaN
and every seventh x infinite, on 30,000 points, and on the real KITTI and HDL-32 scans
of ../shared/realdata when present: `layout_problem` (the points) and `check_layout`
(with the file's first bytes read, as `read_scan` runs it).

The second part measures how much of an organized cloud would be "no return" (the
share `plausible.MAX_NO_RETURN` bounds) on the real scans: a KITTI HDL-64E scan put
into its 64-ring image (rings where the azimuth wraps, columns of the median azimuth
step), the HDL-32E pair's stored zero points and its 32-ring image, and the simulator's
HDL-32E rays in the bundled samples.

    nice -n 10 .venv/bin/python benchmarks/bench_layout_check.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from _common import REALDATA, REPO, median_ms, print_header

from disco_cli.io.readers.plausible import check_layout, layout_problem

SAMPLE_SCAN = REPO / "data/samples/01/velodyne/000005.bin"
KITTI = sorted((REALDATA / "kitti00/velodyne").glob("*.bin"))
HDL32 = sorted((REALDATA / "hdl32_pair").glob("*.bin"))


def _scans() -> dict[str, np.ndarray]:
    scans: dict[str, np.ndarray] = {}
    sample = np.fromfile(SAMPLE_SCAN, "<f4").reshape(-1, 4)
    scans[f"sample 01/000005 ({len(sample)} points)"] = sample
    pattern = np.resize(sample, (25944, 4)).copy()
    pattern[::3, :3] = np.nan
    pattern[::7, 0] = np.inf
    scans["25,944 points, every 3rd NaN, every 7th x inf"] = pattern
    rng = np.random.default_rng(0)
    scans["30,000 points"] = np.resize(sample, (30000, 4))[rng.permutation(30000)]
    for name, paths in (("KITTI 00/000000", KITTI), ("HDL-32 source", HDL32[:1])):
        if paths:
            pts = np.fromfile(paths[0], "<f4").reshape(-1, 4)
            scans[f"{name} ({len(pts)} points)"] = pts
    return scans


def timings() -> None:
    print("median time of the check, 2000 runs each:")
    print(f"{'scan':48s} {'layout_problem':>14s} {'check_layout':>13s}  verdict")
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, pts) in enumerate(_scans().items()):
            path = Path(tmp) / f"{k}.bin"
            pts.astype("<f4").tofile(path)
            ms = median_ms(lambda: layout_problem(pts), repeats=2000, warmup=50)
            ms_file = median_ms(lambda: check_layout(path, pts, "kitti"), repeats=2000, warmup=50)
            print(f"{name:48s} {ms:11.3f} ms {ms_file:10.3f} ms  {layout_problem(pts) or 'passes'}")


def _empty_cells(ring: np.ndarray, azimuth: np.ndarray, columns: int) -> float:
    """The share of a rings x columns image that no point falls in."""
    col = np.floor((azimuth + np.pi) / (2 * np.pi) * columns).astype(np.int64) % columns
    return 1.0 - len(np.unique(ring * columns + col)) / ((ring.max() + 1) * columns)


def _median_step(ring: np.ndarray, azimuth: np.ndarray) -> float:
    steps = [np.diff(np.sort(azimuth[ring == r])) for r in np.unique(ring)]
    steps = np.concatenate(steps)
    return float(np.median(steps[steps > 1e-6]))


def _kitti_rings(azimuth: np.ndarray) -> np.ndarray:
    """KITTI stores a scan ring after ring, each turning once: a ring starts where the
    azimuth wraps (segments of 100 points or fewer are jitter at the wrap, kept with the
    ring before; the last, partial ring is the first one's start)."""
    start = np.zeros(len(azimuth), np.int64)
    start[np.flatnonzero(np.diff(azimuth) < -np.pi) + 1] = 1
    segment = np.cumsum(start)
    ring = np.maximum(np.cumsum(np.bincount(segment) > 100) - 1, 0)[segment]
    ring[ring == ring.max()] = 0
    return ring


def no_return_shares() -> None:
    print("\nno return on real layouts (the share plausible.MAX_NO_RETURN bounds):")
    for path in KITTI:
        p = np.fromfile(path, "<f4").reshape(-1, 4)
        az = np.arctan2(p[:, 1], p[:, 0])
        ring = _kitti_rings(az)
        columns = round(2 * np.pi / _median_step(ring, az))
        print(
            f"KITTI HDL-64E {path.name}: {len(p)} points, {ring.max() + 1} x {columns} image, "
            f"{_empty_cells(ring, az, columns):.1%} of it empty"
        )
    for path in HDL32:
        p = np.fromfile(path, "<f4").reshape(-1, 4)
        zero = np.abs(p[:, :3]).max(axis=1) < 1e-3
        q = p[~zero]
        elevation = np.degrees(np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1])))
        ring = np.unique(np.round(elevation, 1), return_inverse=True)[1]
        az = np.arctan2(q[:, 1], q[:, 0])
        columns = round(2 * np.pi / _median_step(ring, az))
        print(
            f"HDL-32E {path.name}: {zero.mean():.1%} of its {len(p)} points are zeros; "
            f"{ring.max() + 1} x {columns} image, {_empty_cells(ring, az, columns):.1%} empty"
        )
    sample = np.fromfile(SAMPLE_SCAN, "<f4").reshape(-1, 4)
    rays = 32 * 600  # the samples' simulated HDL-32E: 32 beams, 0.6 degree azimuth step
    print(f"simulated HDL-32E (sample 01/000005): {1 - len(sample) / rays:.1%} of {rays} rays")


def main() -> None:
    print_header("scan check")
    timings()
    if KITTI or HDL32:
        no_return_shares()
    else:
        print(f"\n{REALDATA} is absent: no real layouts to measure")


if __name__ == "__main__":
    main()
