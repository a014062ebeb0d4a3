"""Map database writes and reads at scale: rows/s of appends from the first rows to N.

    .venv/bin/python benchmarks/bench_db_rows.py [--rows 200000] [--batch 32] [--dir DIR]
        [--features-from MAP]

Rows go straight through `Database.append` (no scans, no network), in batches of
`--batch` as build-db writes them: a random unit signature (1024) and a feature pair of
the `default` model's shape (2 x 40 x 120) drawn from a pool embedded once from
synthetic scans, or read from the map `--features-from` (so they deflate as real
features do). Times are CPU time of this thread (`time.thread_time`: encoding, SQLite's
writes to the page cache), so that other processes on a busy machine do not blur them;
the overall wall-clock rate is printed too. Printed:

1. rows/s (median over batches) over the first and the last 5 % of the rows, and their
   ratio: a write path with anything O(N) per insert (a COUNT, a full read, an index
   that grows badly) slows down towards the end;
2. bytes per row of the file at N;
3. at N: `Database.open` + `signatures()` (the load a query makes once), `rows()` of 40
   random ids (what re-ranking reads per query at its widest), of 40 ids that slide by
   one per query (a stream of queries along the map, whose rows `rows()` keeps
   decoded), and decoding 40 stored
   feature pairs against the same pairs stored raw (float16, no deflate), interleaved in
   this process: what the compression costs a query.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
from _common import cpu_model, model_arg, print_header, synthetic_scan


def feature_pool(n: int, tmp: Path) -> tuple[np.ndarray, str]:
    """`[n, 2, 40, 120]` features of the default architecture from synthetic scans."""
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    name, what = model_arg("default", tmp)
    model = load_model(name)
    bevs = np.stack([polar_bev(synthetic_scan(s), model.bev_config) for s in range(n)])
    _, feats = model.embed(bevs)
    return np.asarray(feats, np.float32), f"from synthetic scans, {what} model"


def stored_pool(path: Path) -> tuple[np.ndarray, str]:
    """The features stored in an existing map (up to 64 of them)."""
    from disco_cli.maps.database import Database

    with Database.open(path) as db:
        ids, _ = db.signatures()
        return db.rows(ids[:64]).features, f"stored in {path}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--dir", type=Path, default=None, help="where the map is written")
    ap.add_argument("--features-from", type=Path, default=None, help="a map to take features from")
    args = ap.parse_args()
    try:
        print_header("bench_db_rows")
    except ImportError:  # no compiled core for this Python: the CPU line alone
        print(f"# bench_db_rows on machine: {cpu_model()}, {os.cpu_count()} cores")

    from disco_cli.maps.database import Database, ModelInfo, ScanBatch

    with tempfile.TemporaryDirectory(dir=args.dir) as tmpdir:
        tmp = Path(tmpdir)
        if args.features_from is not None:
            pool, what = stored_pool(args.features_from)
        else:
            pool, what = feature_pool(32, tmp)
        print(f"features: a pool of {len(pool)} ({what})")
        rng = np.random.default_rng(0)
        info = ModelInfo("bench", "0" * 64, {}, {})
        path = tmp / "map.db"
        db = None
        rates: list[tuple[int, float]] = []
        done = 0
        t_all = time.thread_time()
        wall = time.perf_counter()
        while done < args.rows:
            b = min(args.batch, args.rows - done)
            sigs = rng.normal(size=(b, 1024)).astype(np.float32)
            sigs /= np.linalg.norm(sigs, axis=1, keepdims=True)
            batch = ScanBatch(
                paths=[f"/data/run/{done + i:09d}.bin" for i in range(b)],
                signatures=sigs,
                features=pool[rng.integers(0, len(pool), b)],
                poses=rng.normal(size=(b, 4)),
                times=np.arange(done, done + b) * 0.1,
            )
            t = time.thread_time()
            if db is None:
                db = Database.create(path, info, batch)
            else:
                db.append(batch)
            rates.append((done, b / (time.thread_time() - t)))
            done += b
            if done % 50_000 < b:
                print(f"  {done} rows, {time.perf_counter() - wall:.0f} s", flush=True)
        db.close()  # type: ignore[union-attr]
        window = max(1, len(rates) // 20)
        first = float(np.median([r for _, r in rates[:window]]))
        last = float(np.median([r for _, r in rates[-window:]]))
        size = path.stat().st_size
        print(
            f"append: {first:.0f} rows/s over the first {window * args.batch} rows, "
            f"{last:.0f} rows/s over the last {window * args.batch} (of {done}): "
            f"ratio {last / first:.2f}; overall {done / (time.thread_time() - t_all):.0f} rows/s "
            f"of CPU, {done / (time.perf_counter() - wall):.0f} rows/s of wall-clock time"
        )
        print(f"file: {size} bytes, {size / done:.0f} bytes per row ({size / done / 1024:.2f} KiB)")

        t = time.thread_time()
        with Database.open(path, verify=False) as db:
            ids, _ = db.signatures()
            load = time.thread_time() - t
            assert len(ids) == done
            picks = [rng.choice(ids, 40, replace=False) for _ in range(100)]
            db.rows(picks[0])  # warm the page cache
            read = []
            for p in picks:
                t = time.thread_time()
                db.rows(p)
                read.append(time.thread_time() - t)
            # A streaming query's re-ranked neighbours: 40 ids sliding by one per query,
            # most of them read (and kept decoded) by the query before.
            start = int(rng.integers(0, done - 200))
            slide = []
            for q in range(100):
                t = time.thread_time()
                db.rows(ids[start + q : start + q + 40])
                slide.append(time.thread_time() - t)
            blobs = [
                r[0]
                for r in db._conn.execute("SELECT data FROM features WHERE id <= 40").fetchall()
            ]
        raw = [zlib.decompress(b, -15) for b in blobs]
        inflate, plain = [], []
        for _ in range(100):  # interleaved: the same load on both
            t = time.thread_time()
            for b in blobs:
                np.frombuffer(zlib.decompress(b, -15), "<f2").astype(np.float32)
            inflate.append(time.thread_time() - t)
            t = time.thread_time()
            for b in raw:
                np.frombuffer(b, "<f2").astype(np.float32)
            plain.append(time.thread_time() - t)
        print(f"open + signatures() of {done} rows: {load:.2f} s")
        print(
            f"rows() of 40 ids sliding by one per query (a stream): "
            f"{np.median(slide) * 1e3:.2f} ms (median of 100)"
        )
        print(
            f"rows() of 40 random ids: {np.median(read) * 1e3:.2f} ms (median of 100); "
            f"decoding 40 feature pairs: {np.median(inflate) * 1e3:.2f} ms deflated vs "
            f"{np.median(plain) * 1e3:.2f} ms stored raw (medians of 100, interleaved)"
        )


if __name__ == "__main__":
    main()
