"""Opening a large map: what `Database.open` costs, and a fresh process's first answer.

    .venv/bin/python benchmarks/bench_open.py [--rows 200000] [--dir DIR] [--repeat 7]

A map of `--rows` rows of the `spectral` model (1024-value signatures, 40 x 120
features) is written through `Database.create`/`append` in batches of 256, once: the
file is kept in `--dir` (default: the system's temporary folder) and reused while it
holds that many rows. The rows' features, cycled, and the signatures of the first rows
are those of the 52 KITTI scans in data/samples (else of 64 synthetic scans), so that
they deflate as real ones do; the other signatures are random unit vectors. The query
is the sixth of those scans, which the map holds as row 6.

Printed, page cache warm (as right after building; a cold cache adds the reads of the
pages touched):

1. `Database.open` + `close` (header, meta and schema: what every command does), the
   median of `--repeat`, and the same with `verify=True` (SQLite's integrity check over
   the whole file, what every open did before), the median of 3;
2. a fresh process (`python -c`, imports not counted) that opens the map with
   `Map.open` (the model loaded too), then answers one query
   (reading the signatures of every row, building the index, searching, re-ranking):
   the median of `--repeat` processes, each phase apart.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import REPO, print_header, synthetic_scan

BATCH = 256
SAMPLES = REPO / "data" / "samples"


def pool_scans() -> list[np.ndarray]:
    """The scans whose embeddings fill the map: data/samples' KITTI scans (their
    features deflate as real ones do), else 64 synthetic ones."""
    from disco_cli import read_scan

    files = sorted(SAMPLES.glob("*/velodyne/*.bin"))
    if files:
        return [read_scan(str(f)) for f in files]
    return [synthetic_scan(s) for s in range(64)]


def build(path: Path, rows: int) -> None:
    """The map at `path`: `rows` rows written through the Database API."""
    from disco_cli import load_model, signature
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch

    model = load_model("spectral")
    embedded = [signature(model, points) for points in pool_scans()]
    pool_sigs = np.stack([e[0] for e in embedded]).astype(np.float32)
    pool_feats = np.stack([e[1] for e in embedded]).astype(np.float32)
    rng = np.random.default_rng(0)
    tmp = path.with_name(path.name + ".building")
    for suffix in ("", "-wal", "-shm"):
        Path(f"{tmp}{suffix}").unlink(missing_ok=True)
    db = None
    t0 = time.perf_counter()
    for start in range(0, rows, BATCH):
        n = min(BATCH, rows - start)
        sigs = rng.normal(size=(n, pool_sigs.shape[1])).astype(np.float32)
        sigs /= np.linalg.norm(sigs, axis=1, keepdims=True)
        pool = len(pool_sigs)
        real = [k for k in range(n) if start + k < pool]
        sigs[real] = pool_sigs[[start + k for k in real]]
        batch = ScanBatch(
            paths=[f"/synthetic/{start + k:07d}.bin" for k in range(n)],
            signatures=sigs,
            features=pool_feats[[(start + k) % pool for k in range(n)]],
        )
        if db is None:
            extra = {"model_source": "spectral"}
            db = Database.create(tmp, ModelInfo.of(model), batch, extra_meta=extra)
        else:
            db.append(batch)
        if (start // BATCH) % 100 == 0:
            print(f"  writing: {start + n} rows, {time.perf_counter() - t0:.0f} s", flush=True)
    assert db is not None
    db.close()
    os.replace(tmp, path)


def rows_in(path: Path) -> int:
    from disco_cli.errors import DatabaseError
    from disco_cli.maps.database import Database

    try:
        with Database.open(path) as db:
            return len(db)
    except DatabaseError:
        return -1


# One fresh process: open the map, answer one query; seconds of each, as JSON.
CHILD = """
import json, sys, time
sys.path.insert(0, sys.argv[2])
from bench_open import pool_scans
from disco_cli.maps.facade import Map
points = pool_scans()[5]
t0 = time.perf_counter()
m = Map.open(sys.argv[1])
t1 = time.perf_counter()
found = m.query(points, topk=1)
t2 = time.perf_counter()
m.close()
print(json.dumps({"open": t1 - t0, "query": t2 - t1, "match": found[0].name}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    print_header("bench_open")
    from disco_cli.maps.database import Database

    path = args.dir / f"bench-open-{args.rows}.db"
    if rows_in(path) != args.rows:
        print(f"building {path} ({args.rows} rows)", flush=True)
        build(path, args.rows)
    size = path.stat().st_size
    print(f"map: {path}, {args.rows} rows, {size:,} bytes ({size / args.rows:,.0f} per row)")

    def open_close(verify: bool) -> float:
        t0 = time.perf_counter()
        Database.open(path, verify=verify).close()
        return time.perf_counter() - t0

    open_close(False)
    cheap = [open_close(False) for _ in range(args.repeat)]
    full = [open_close(True) for _ in range(3)]
    print(
        f"Database.open + close: median {statistics.median(cheap) * 1e3:.1f} ms "
        f"(min {min(cheap) * 1e3:.1f}, max {max(cheap) * 1e3:.1f}, {args.repeat} runs); "
        f"with verify=True (the integrity check): median {statistics.median(full) * 1e3:.0f} ms"
    )
    runs = []
    for _ in range(args.repeat):
        out = subprocess.run(
            [sys.executable, "-c", CHILD, str(path), str(Path(__file__).parent)],
            capture_output=True,
            text=True,
            check=True,
        )
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    opens = [r["open"] for r in runs]
    queries = [r["query"] for r in runs]
    print(
        f"fresh process, Map.open (model loaded): median {statistics.median(opens) * 1e3:.0f} ms "
        f"(min {min(opens) * 1e3:.0f}, max {max(opens) * 1e3:.0f}); first query (every "
        f"signature read and verified, index built, search, re-rank): median "
        f"{statistics.median(queries):.2f} s (min {min(queries):.2f}, max {max(queries):.2f}); "
        f"{args.repeat} processes; top match {runs[0]['match']}"
    )


if __name__ == "__main__":
    main()
