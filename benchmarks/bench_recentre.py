"""The compiled yaw searches' kernel alone: `_core.recentre_search` per call.

    .venv/bin/python benchmarks/bench_recentre.py [--pairs 8] [--rounds 40]

Synthetic scans (`_common.synthetic_scan`), each paired with itself moved a few metres
and turned, go through `yaw_refine.refine_checked` once with the kernel wrapped, which
keeps the arguments of every call that ran its rounds to the end (the places it read
were all kept). Those calls are then replayed, each from the lattice state it started
from (its curves not yet done), at every kernel level the CPU has (forced), interleaved:
microseconds per call and per view computed (a view: one position's reads, transform,
whitened cross-power and curve; about 31 per call).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

LEVEL_NAMES = {3: "avx512", 2: "avx2", 1: "sse2", 0: "plain"}


def moved(points: np.ndarray, xy: tuple[float, float], yaw_deg: float) -> np.ndarray:
    """The scan as a sensor at `xy` (in the scan's frame) headed `yaw_deg` sees it."""
    a = np.radians(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    dx, dy = points[:, 0] - xy[0], points[:, 1] - xy[1]
    out = points.copy()
    out[:, 0], out[:, 1] = c * dx + s * dy, -s * dx + c * dy
    return out


def captured_calls(pairs: int) -> list[tuple]:
    """(arguments, the lattice's done flags before, its answer, the views it computed)
    of each call that ran to the end."""
    from _common import synthetic_scan

    from disco_cli import _core
    from disco_cli.model import yaw_refine
    from disco_cli.model.bev import BEVConfig, polar_bev

    cfg = BEVConfig()
    calls = []
    kernel = _core.recentre_search

    def keep(*args):
        done = args[9].copy()
        out = kernel(*args)
        if not out[0]:
            calls.append((args, done, out, int(args[9].sum() - done.sum())))
        return out

    rng = np.random.default_rng(7)
    images = []
    for i in range(pairs):
        points = synthetic_scan(300 + i)
        xy = tuple(rng.uniform(-4.0, 4.0, 2))
        query = polar_bev(moved(points, xy, rng.uniform(-180, 180)), cfg).sum(axis=0)
        images.append((query, polar_bev(points, cfg).sum(axis=0)))
    # Once to keep the places of every position the searches visit (as a stream of
    # queries soon has them), then once captured: each search in one call.
    for wrapped in (kernel, keep):
        _core.recentre_search = wrapped
        try:
            for query, match in images:
                yaw_refine.forget_kept_views()
                yaw_refine.refine_checked(query, match, cfg.max_range)
        finally:
            _core.recentre_search = kernel
    return calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=40)
    args = ap.parse_args()
    from _common import interleaved_medians_ms, print_header

    from disco_cli import _core

    print_header("bench_recentre")
    calls = captured_calls(args.pairs)
    for a, done, out, _ in calls:  # the places it read still kept: the same answer
        np.copyto(a[9], done)
        if _core.recentre_search(*a) != out:
            sys.exit("bench_recentre: a replayed call's answer differs")
    views = sum(c[3] for c in calls)

    def replay(level: int):
        def run():
            _core._set_bev_kernel_level(level)
            for a, done, _, _ in calls:
                np.copyto(a[9], done)  # its curves not yet done: computed again
                _core.recentre_search(*a)

        return run

    cap = _core._set_bev_kernel_level(3)
    levels = {}
    for level in (3, 2, 1, 0):
        _core._set_bev_kernel_level(level)
        levels.setdefault(LEVEL_NAMES[_core._bev_kernel_level()], level)
    try:
        ms = interleaved_medians_ms({n: replay(lv) for n, lv in levels.items()}, args.rounds, 1)
    finally:
        _core._set_bev_kernel_level(cap)
    per = ", ".join(
        f"{n} {1e3 * t / len(calls):.0f} us a call ({1e3 * t / views:.2f} us a view)"
        for n, t in ms.items()
    )
    print(
        f"recentre_search, {len(calls)} calls of refine_checked on {args.pairs} synthetic "
        f"pairs ({views} views), replayed at each kernel level (forced), interleaved "
        f"medians: {per}"
    )


if __name__ == "__main__":
    main()
