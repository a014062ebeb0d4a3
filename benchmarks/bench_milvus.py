"""A map in Milvus Lite (issue 33): insert rate, per-query search time, memory and recall.

    .venv/bin/python benchmarks/bench_milvus.py scale --n 100000 [--queries 200]
        [--index flat|hnsw] [--out out/milvus]
    .venv/bin/python benchmarks/bench_milvus.py world [--out out/milvus-world]

`scale`: N synthetic scans written through disco's own writer (`MilvusDatabase.append`,
batches of 1,000) into a fresh Milvus Lite folder, then searched by `MilvusIndex` (what
`disco query` on a `milvus:` map uses). The signatures are synthetic, NOT embeddings of
real scans: 1024-d unit vectors clustered around 2,000 random centres (noise 0.5 of the
centre's norm), rounded to float16 as every map stores them. Every row carries real
feature images (the 26 bundled scans of session 00, embedded by the default model and
repeated), so each row has the size a real one has. The queries are map rows plus
noise. Measured:

- insert: scans/s over the whole fill (encoding, checksums and Milvus's insert);
- index: seconds to build the HNSW index (`--index hnsw`; FLAT has none to build);
- search: median and 95th percentile ms per query, top 10, one query at a time, both
  Milvus's own search call and `MilvusIndex.search` (which re-measures the candidates
  exactly and maps them to rows);
- recall@1 / @10 of `MilvusIndex.search` against an exact NumPy search (float64) of the
  same float16-rounded vectors;
- memory: this process's resident size (Milvus Lite runs inside it) after the fill and
  after loading the collection; the folder's bytes on disk.

`world`: the whole query on a held-out simulated town (seed 8107, two sessions of 332 m):
the SQLite map of session 00 is built, copied into Milvus Lite (`build-db --from`), and
60 evenly spaced scans of session 01 are queried against both, the Milvus map searched
in process (`auto` at this size) and by Milvus itself (`--index ann`): how many top-1
answers agree with the SQLite map's, each one's Recall@1 (the top-1 within 5 m of the
query's true position), and the mean time per query (embedding included).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import REPO, print_header, rss_mib

DISCO = [sys.executable, "-m", "disco_cli.cli"]


def real_rows(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """Signatures and features of the 26 bundled scans (an SQLite map built once)."""
    from disco_cli.maps.database import Database

    db_path = out / "samples.db"
    if not db_path.exists():
        subprocess.run(
            [*DISCO, "build-db", str(REPO / "data/samples/00"), "-o", str(db_path)], check=True
        )
    with Database.open(db_path) as db:
        ids, sigs = db.signatures()
        return sigs, db.rows(ids).features


def synthetic(n: int, dim: int, seed: int = 0) -> np.ndarray:
    """`n` clustered unit vectors, rounded to float16 (what a map stores)."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((2000, dim)).astype(np.float32)
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    out = np.empty((n, dim), np.float32)
    for s in range(0, n, 50_000):
        m = min(50_000, n - s)
        v = centres[rng.integers(0, len(centres), m)]
        v = v + 0.5 / np.sqrt(dim) * rng.standard_normal((m, dim)).astype(np.float32)
        out[s : s + m] = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out.astype(np.float16).astype(np.float32)


def scale(args: argparse.Namespace) -> dict:
    import disco_cli.maps.milvus_store as store
    from disco_cli.maps.database import ModelInfo, ScanBatch
    from disco_cli.maps.milvus_index import MilvusIndex
    from disco_cli.model import load_model

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sigs_real, feats_real = real_rows(out)
    dim = sigs_real.shape[1]
    sigs = synthetic(args.n, dim)
    folder = out / f"bench-{args.n}.db"
    address = f"milvus:{folder}"
    model = ModelInfo.of(load_model("default"))
    # Filled under FLAT; HNSW, when asked, is built over the whole fill afterwards.
    store.HNSW_MIN_ROWS = 10**12
    rss0 = rss_mib()

    def batch(s: int, e: int) -> ScanBatch:
        k = np.arange(s, e)
        return ScanBatch(
            paths=[f"/fleet/scan-{i:07d}.bin" for i in k],
            signatures=sigs[s:e],
            features=feats_real[k % len(feats_real)],
            poses=np.stack([k * 1.0, k * 0.0, k * 0.0, k * 0.0], axis=1),
            times=k * 0.1,
        )

    step = 1000
    start = time.perf_counter()
    reused = args.reuse and folder.exists()
    if reused:  # a fill of an earlier run (its figures stand)
        db = store.MilvusDatabase.open(address, writable=True)
        assert len(db) == args.n, f"{folder} holds {len(db)} scans, not {args.n}"
    else:
        shutil.rmtree(folder, ignore_errors=True)
        db = store.MilvusDatabase.create(address, model, batch(0, min(step, args.n)))
        for s in range(step, args.n, step):
            db.append(batch(s, min(s + step, args.n)))
            if s % 50_000 == 0:
                print(f"  {s} rows, {time.perf_counter() - start:.0f} s", flush=True)
    fill_s = None if reused else time.perf_counter() - start
    index_s = 0.0
    if args.index == "hnsw":
        store.HNSW_MIN_ROWS = 1
        t = time.perf_counter()
        db._choose_index()
        index_s = time.perf_counter() - t
    rss_fill = rss_mib()
    db.close()
    # A fresh open, as a query process would (Milvus Lite loads its segments).
    t = time.perf_counter()
    db = store.MilvusDatabase.open(address)
    ids = db.ids()
    open_s = time.perf_counter() - t
    index = MilvusIndex(db, ids)
    rng = np.random.default_rng(1)
    picks = rng.choice(args.n, args.queries, replace=False)
    queries = sigs[picks] + 0.3 / np.sqrt(dim) * rng.standard_normal((args.queries, dim))
    queries = queries.astype(np.float32)
    raw_ms, ms, r1, r10 = [], [], [], []
    sq = (sigs.astype(np.float64) ** 2).sum(axis=1)
    for q in queries:
        t = time.perf_counter()
        index._milvus_search(q, 10, f"id <= {int(ids[-1])}")
        raw_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        rows, _ = index.search(q, 10)
        ms.append((time.perf_counter() - t) * 1e3)
        d = sq - 2.0 * sigs.astype(np.float64) @ q.astype(np.float64)
        exact = np.argsort(d, kind="stable")[:10]
        r1.append(rows[0] == exact[0])
        r10.append(len(set(rows.tolist()) & set(exact.tolist())) / 10)
    rss_open = rss_mib()
    db.close()
    disk = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    result = {
        "n": args.n,
        "index": args.index,
        "queries": args.queries,
        "insert_scans_per_s": fill_s and round(args.n / fill_s, 1),
        "fill_s": fill_s and round(fill_s, 1),
        "index_build_s": round(index_s, 1),
        "open_s": round(open_s, 2),
        "milvus_search_ms_median": round(float(np.median(raw_ms)), 2),
        "milvus_search_ms_p95": round(float(np.percentile(raw_ms, 95)), 2),
        "index_search_ms_median": round(float(np.median(ms)), 2),
        "index_search_ms_p95": round(float(np.percentile(ms, 95)), 2),
        "recall_at_1": round(float(np.mean(r1)), 4),
        "recall_at_10": round(float(np.mean(r10)), 4),
        "rss_growth_fill_mib": round(rss_fill - rss0, 0),
        "rss_after_open_mib": round(rss_open, 0),
        "disk_mib": round(disk / 2**20, 1),
        "bytes_per_scan": round(disk / args.n),
    }
    return result


def world(args: argparse.Namespace) -> dict:
    from disco_cli.maps.facade import Map

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    town = out / "town"
    if not (town / "01").exists():
        subprocess.run(
            [
                *DISCO,
                "simulate",
                str(town),
                "--sessions",
                "2",
                "--length-m",
                "332",
                "--seed",
                "8107",
                "--force",
            ],
            check=True,
        )
    sqlite_map, milvus_dir = out / "map.db", out / "fleet.db"
    if not sqlite_map.exists():
        subprocess.run([*DISCO, "build-db", str(town / "00"), "-o", str(sqlite_map)], check=True)
    shutil.rmtree(milvus_dir, ignore_errors=True)
    t = time.perf_counter()
    subprocess.run(
        [*DISCO, "build-db", "--from", str(sqlite_map), "-o", f"milvus:{milvus_dir}"], check=True
    )
    copy_s = time.perf_counter() - t
    scans = sorted((town / "01" / "velodyne").iterdir())
    picks = np.linspace(0, len(scans) - 1, args.queries).round().astype(int)
    queries = [str(scans[i]) for i in picks]
    truth = np.loadtxt(town / "01" / "poses.txt").reshape(-1, 3, 4)[picks, :, 3]
    top1, seconds = {}, {}
    runs = (
        ("sqlite", sqlite_map, "auto"),
        ("milvus", f"milvus:{milvus_dir}", "auto"),
        ("milvus_ann", f"milvus:{milvus_dir}", "ann"),
    )
    for name, db, index in runs:
        with Map.open(db, index=index) as m:
            t = time.perf_counter()
            top1[name] = [
                res.matches[0] if res.matches else None
                for res in m.query_files(queries, topk=1, threads=1)
            ]
            seconds[name] = time.perf_counter() - t
    map_poses = np.loadtxt(town / "00" / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    names = sorted(str(p) for p in (town / "00" / "velodyne").iterdir())
    where = {n: map_poses[i] for i, n in enumerate(names)}

    def correct(match, q: int) -> bool:
        if match is None:
            return False
        return float(np.linalg.norm(where[match.name][:2] - truth[q][:2])) <= 5.0

    def agree(other: str) -> int:
        return sum(
            a is not None and b is not None and a.name == b.name
            for a, b in zip(top1["sqlite"], top1[other])
        )

    gaps = np.linalg.norm(map_poses[None, :, :2] - truth[:, None, :2], axis=2).min(axis=1)
    out = {
        "map_scans": len(names),
        "queries": len(queries),
        "queries_with_a_map_scan_within_5m": int((gaps <= 5.0).sum()),
        "copy_s": round(copy_s, 1),
    }
    for name in top1:
        out[f"recall_at_1_{name}"] = sum(correct(m, i) for i, m in enumerate(top1[name]))
        out[f"query_ms_{name}"] = round(seconds[name] / len(queries) * 1e3, 1)
        if name != "sqlite":
            out[f"top1_agree_{name}"] = agree(name)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    s = sub.add_parser("scale")
    s.add_argument("--n", type=int, default=100_000)
    s.add_argument("--queries", type=int, default=200)
    s.add_argument("--index", choices=("flat", "hnsw"), default="flat")
    s.add_argument("--out", default="out/milvus")
    s.add_argument("--reuse", action="store_true", help="search the fill of an earlier run")
    w = sub.add_parser("world")
    w.add_argument("--queries", type=int, default=60)
    w.add_argument("--out", default="out/milvus-world")
    args = p.parse_args()
    print_header(f"bench_milvus {args.what}")
    result = scale(args) if args.what == "scale" else world(args)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
