"""build-db throughput: scans/s of `disco build-db` on 30k-point scans.

    .venv/bin/python benchmarks/bench_build_db.py [--scans 300] [--model default]
        [--side-views 2.5]

The `default` model when its weights are shipped; until then a checkpoint of the same
architecture with untrained weights (the same compute). Scans are written to a temp
folder first (30k points each: boxes and poles around the sensor). Measured:

1. `disco build-db` as a user runs it (fresh process; the rate it prints covers
   reading, voxelizing, the network and writing, overlapped), for --threads 1 and 2;
2. the baseline in this process: the same stages one after the other, no overlap;
3. with --side-views M: `disco build-db --side-views M` against the same command
   without, in rate and file size.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import model_arg, print_header, synthetic_scan


def run_cli(
    scans: Path, out: Path, model: str, workers: int, batch: int, extra: tuple[str, ...] = ()
) -> tuple[float, float]:
    exe = Path(sys.executable).parent / "disco"
    t = time.perf_counter()
    proc = subprocess.run(
        [
            str(exe),
            "build-db",
            str(scans),
            "-o",
            str(out),
            "--model",
            model,
            "--threads",
            str(workers),
            "--batch",
            str(batch),
            *extra,
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    wall = time.perf_counter() - t
    m = re.search(r"\(([\d.]+) scans/s\)", proc.stderr)
    return float(m.group(1)) if m else float("nan"), wall


def serial_baseline(paths: list[Path], model_name: str, batch: int, out: Path) -> dict:
    from disco_cli.io.readers import read_scan
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    model = load_model(model_name)
    info = ModelInfo.of(model)
    t_read = t_bev = t_net = t_write = 0.0
    db = None
    start = time.perf_counter()
    for s in range(0, len(paths), batch):
        chunk = paths[s : s + batch]
        t0 = time.perf_counter()
        pts = [read_scan(p) for p in chunk]
        t1 = time.perf_counter()
        bevs = np.stack([polar_bev(p, model.bev_config) for p in pts])
        t2 = time.perf_counter()
        sigs, feats = model.embed(bevs)
        t3 = time.perf_counter()
        b = ScanBatch([str(p) for p in chunk], sigs, feats)
        if db is None:
            db = Database.create(out, info, b)
        else:
            db.append(b)
        t4 = time.perf_counter()
        t_read += t1 - t0
        t_bev += t2 - t1
        t_net += t3 - t2
        t_write += t4 - t3
    db.close()
    total = time.perf_counter() - start
    n = len(paths)
    return {
        "rate": n / total,
        "read_ms": 1e3 * t_read / n,
        "bev_ms": 1e3 * t_bev / n,
        "net_ms": 1e3 * t_net / n,
        "write_ms": 1e3 * t_write / n,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=300)
    ap.add_argument("--points", type=int, default=30000)
    ap.add_argument("--model", default="default")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--side-views", type=float, default=0.0, help="also time --side-views M")
    args = ap.parse_args()
    import torch

    print_header("bench_build_db")
    print(f"torch threads: {torch.get_num_threads()}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model, what = model_arg(args.model, tmp)
        scans = tmp / "scans"
        scans.mkdir()
        paths = []
        for i in range(args.scans):
            p = scans / f"{i:06d}.bin"
            synthetic_scan(i, args.points).tofile(p)
            paths.append(p)
        print(f"{args.scans} scans of {args.points} points; model: {what}")
        base = serial_baseline(paths, model, args.batch, tmp / "serial.db")
        print(
            f"serial baseline (this process): {base['rate']:.1f} scans/s = read "
            f"{base['read_ms']:.2f} + voxelize {base['bev_ms']:.2f} + network "
            f"{base['net_ms']:.2f} + write {base['write_ms']:.2f} ms/scan"
        )
        for workers in (1, 2):
            rate, wall = run_cli(scans, tmp / f"cli{workers}.db", model, workers, args.batch)
            print(
                f"disco build-db --threads {workers} --batch {args.batch}: {rate:.1f} scans/s "
                f"(as printed; {args.scans / wall:.1f} scans/s including process start, "
                f"{wall:.1f} s wall); {rate / base['rate']:.2f}x the serial baseline"
            )
        if args.side_views > 0:
            plain_rate, _ = run_cli(scans, tmp / "plain.db", model, 1, args.batch)
            sv = ("--side-views", f"{args.side_views:g}")
            rate, _ = run_cli(scans, tmp / "sv.db", model, 1, args.batch, sv)
            size = (tmp / "sv.db").stat().st_size / (tmp / "plain.db").stat().st_size
            print(
                f"disco build-db --threads 1 --side-views {args.side_views:g}: {rate:.1f} "
                f"scans/s against {plain_rate:.1f} without ({rate / plain_rate:.2f}x, run "
                f"just before); file {size:.2f}x the size"
            )


if __name__ == "__main__":
    main()
