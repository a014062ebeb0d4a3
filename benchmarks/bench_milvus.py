"""A map in Milvus Lite (issue 33): insert rate, per-query search time, memory and recall.

    .venv/bin/python benchmarks/bench_milvus.py scale --n 100000 [--queries 200]
        [--index flat|hnsw] [--features real|zero] [--reuse] [--max-fill-s S]
        [--min-available-gib G] [--out out/milvus]
    .venv/bin/python benchmarks/bench_milvus.py world [--out out/milvus-world]

`scale`: N synthetic scans written through disco's own writer (`MilvusDatabase.append`,
batches of 1,000 or `--batch`) into a fresh Milvus Lite folder, then searched by `MilvusIndex` (what
`disco query` on a `milvus:` map uses). The signatures are synthetic, NOT embeddings of
real scans: 1024-d unit vectors clustered around 2,000 random centres (noise 0.5 of the
centre's norm), rounded to float16 as every map stores them. Every row carries real
feature images (the 26 bundled scans of session 00, embedded by the default model and
repeated), so each row has the size a real one has; `--features zero` stores all-zero
images of the same shape instead (the field is still written, deflated to a few dozen
bytes), to measure the signatures' side of a map too large for this machine's memory
with real features. The queries are map rows plus noise. Measured:

- insert: scans/s over the whole fill (encoding, checksums and Milvus's insert), and
  the rate, resident memory and the machine's available memory every `--every` rows;
  the fill stops early, and says so, past `--max-fill-s` or under
  `--min-available-gib` (the rest is then measured at the size reached);
- index: seconds to build the HNSW index (`--index hnsw`; FLAT has none to build);
- search: median and 95th percentile ms per query, top 10, one query at a time, both
  Milvus's own search call and `MilvusIndex.search` (which re-measures the candidates
  exactly and maps them to rows);
- recall@1 / @10 of `MilvusIndex.search` against an exact NumPy search (float64) of the
  same float16-rounded vectors;
- memory: the resident size (Milvus Lite runs inside the process) grown by the fill,
  its peak, and in the search process (a fresh one, as `disco query` opens a map)
  grown by opening and at the end; the folder's bytes on disk.

`world`: the whole query on a held-out simulated town (seed 8107, two sessions of 332 m):
the SQLite map of session 00 is built, copied into Milvus Lite (`build-db --from`), and
60 evenly spaced scans of session 01 are queried against both, the Milvus map searched
in process (`auto` at this size) and by Milvus itself (`--index ann`): how many top-1
answers agree with the SQLite map's, each one's Recall@1 (the top-1 within 5 m of the
query's true position), and the mean time per query (embedding included). With
`--server milvus://HOST:PORT` the copy goes to that server's map `world` (replaced)
instead of a Milvus Lite folder, e.g. a `python -m milvus_lite server` started first.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import REPO, peak_rss_mib, print_header, rss_mib

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
    """`n` clustered unit vectors as float16 (what a map stores); held as float16 so
    that a million take 2 GB, not 4."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((2000, dim)).astype(np.float32)
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    out = np.empty((n, dim), np.float16)
    for s in range(0, n, 50_000):
        m = min(50_000, n - s)
        v = centres[rng.integers(0, len(centres), m)]
        v = v + 0.5 / np.sqrt(dim) * rng.standard_normal((m, dim)).astype(np.float32)
        out[s : s + m] = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out


def exact_top(sigs: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """Each query's k nearest rows of `sigs` by exact float64 L2 (ties by row), in
    chunks of rows so that a million float16 rows need no float64 copy."""
    q = queries.astype(np.float64)
    d = np.empty((len(q), len(sigs)))
    for s in range(0, len(sigs), 50_000):
        c = sigs[s : s + 50_000].astype(np.float64)
        d[:, s : s + len(c)] = (c**2).sum(axis=1)[None, :] - 2.0 * q @ c.T
    return np.stack([np.argsort(r, kind="stable")[:k] for r in d])


def mem_available_gib() -> float:
    with open("/proc/meminfo") as fh:
        for line in fh:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 2**20
    return float("inf")


def scale(args: argparse.Namespace) -> dict:
    """The fill (unless `--reuse`) and the index build, in this process; the search in
    a fresh one (`--search-only`), as a query process opens a map."""
    import disco_cli.maps.milvus_store as store
    from disco_cli.maps.database import ModelInfo, ScanBatch
    from disco_cli.model import load_model

    if args.search_only:
        return search_phase(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sigs_real, feats_real = real_rows(out)
    if args.features == "zero":
        feats_real = np.zeros_like(feats_real[:1])
    dim = sigs_real.shape[1]
    folder = out / f"bench-{args.n}.db"
    fill_json = out / f"bench-{args.n}.fill.json"
    address = f"milvus:{folder}"
    # Filled under FLAT; HNSW, when asked, is built over the whole fill afterwards.
    store.HNSW_MIN_ROWS = 10**12
    rss0 = rss_mib()
    step = args.batch
    reused = args.reuse and folder.exists()
    if reused:  # a fill of an earlier run (its figures stand)
        db = store.MilvusDatabase.open(address, writable=True)
        fill = json.loads(fill_json.read_text()) if fill_json.exists() else {"n": len(db)}
    else:
        sigs = synthetic(args.n, dim)
        model = ModelInfo.of(load_model("default"))

        def batch(s: int, e: int) -> ScanBatch:
            k = np.arange(s, e)
            return ScanBatch(
                paths=[f"/fleet/scan-{i:07d}.bin" for i in k],
                signatures=sigs[s:e].astype(np.float32),
                features=feats_real[k % len(feats_real)],
                poses=np.stack([k * 1.0, k * 0.0, k * 0.0, k * 0.0], axis=1),
                times=k * 0.1,
            )

        shutil.rmtree(folder, ignore_errors=True)
        fill_json.unlink(missing_ok=True)
        start = last_t = time.perf_counter()
        db = store.MilvusDatabase.create(address, model, batch(0, min(step, args.n)))
        n, last_n, curve, stopped = min(step, args.n), 0, [], None
        while n < args.n:
            e = min(n + step, args.n)
            db.append(batch(n, e))
            n = e
            elapsed = time.perf_counter() - start
            if n % args.every == 0 or n == args.n:
                now = time.perf_counter()
                point = {
                    "rows": n,
                    "s": round(elapsed, 1),
                    "scans_per_s_since_last": round((n - last_n) / (now - last_t), 1),
                    "rss_mib": round(rss_mib()),
                    "available_gib": round(mem_available_gib(), 1),
                }
                curve.append(point)
                print("  fill", json.dumps(point), flush=True)
                last_n, last_t = n, now
            if args.max_fill_s and elapsed > args.max_fill_s:
                stopped = f"fill stopped at {n} rows: past --max-fill-s {args.max_fill_s}"
            elif mem_available_gib() < args.min_available_gib:
                stopped = f"fill stopped at {n} rows: under {args.min_available_gib} GiB available"
            if stopped:
                print("  " + stopped, flush=True)
                break
        fill_s = time.perf_counter() - start
        fill = {
            "n": n,
            "features": args.features,
            "batch": step,
            "insert_scans_per_s": round(n / fill_s, 1),
            "fill_s": round(fill_s, 1),
            "fill_curve": curve,
            "stopped": stopped,
            "rss_growth_fill_mib": round(rss_mib() - rss0),
        }
        fill_json.write_text(json.dumps(fill))  # kept should the index build fail
    index_s = 0.0
    if args.index == "hnsw" and db.meta.get("index_type") != "HNSW":
        store.HNSW_MIN_ROWS = 1
        t = time.perf_counter()
        db._choose_index()
        index_s = time.perf_counter() - t
    fill["index"] = args.index
    if not reused or index_s:  # else the earlier run's figures stand
        fill.update(index_build_s=round(index_s, 1), peak_rss_fill_mib=round(peak_rss_mib()))
    db.close()
    fill_json.write_text(json.dumps(fill))
    # A fresh process opens and searches the map, as `disco query` would; it replaces
    # this one, whose memory (the fill's, gigabytes at a million scans) goes with it.
    cmd = [sys.executable, __file__, "scale", "--search-only", "--n", str(args.n)]
    cmd += ["--queries", str(args.queries), "--index", args.index, "--out", str(out)]
    sys.stdout.flush()
    os.execv(sys.executable, cmd)


def search_phase(args: argparse.Namespace) -> dict:
    """Open the map in this (fresh) process; time `args.queries` searches, top 10, and
    their recall against an exact search of the same vectors."""
    import disco_cli.maps.milvus_store as store
    from disco_cli.maps.milvus_index import MilvusIndex

    out = Path(args.out)
    folder = out / f"bench-{args.n}.db"
    fill = json.loads((out / f"bench-{args.n}.fill.json").read_text())
    rss0 = rss_mib()
    t = time.perf_counter()
    db = store.MilvusDatabase.open(f"milvus:{folder}")
    ids = db.ids()
    open_s = time.perf_counter() - t
    rss_open = rss_mib()
    n = len(ids)
    assert n == fill["n"], f"{folder} holds {n} scans, its fill wrote {fill['n']}"
    dim = db.signature_dim
    sigs = synthetic(args.n, dim)[:n]  # the same vectors (one seeded stream, in order)
    index = MilvusIndex(db, ids)
    rng = np.random.default_rng(1)
    picks = rng.choice(n, args.queries, replace=False)
    noise = 0.3 / np.sqrt(dim) * rng.standard_normal((args.queries, dim))
    queries = (sigs[picks].astype(np.float32) + noise).astype(np.float32)
    exact = exact_top(sigs, queries, 10)
    raw_ms, ms, r1, r10 = [], [], [], []
    for q, truth in zip(queries, exact):
        t = time.perf_counter()
        index._milvus_search(q, 10, f"id <= {int(ids[-1])}")
        raw_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        rows, _ = index.search(q, 10)
        ms.append((time.perf_counter() - t) * 1e3)
        r1.append(rows[0] == truth[0])
        r10.append(len(set(rows.tolist()) & set(truth.tolist())) / 10)
    rss_search = rss_mib()
    db.close()
    disk = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    return {
        **{k: v for k, v in fill.items() if k != "fill_curve"},
        "queries": args.queries,
        "open_s": round(open_s, 2),
        "milvus_search_ms_median": round(float(np.median(raw_ms)), 2),
        "milvus_search_ms_p95": round(float(np.percentile(raw_ms, 95)), 2),
        "index_search_ms_median": round(float(np.median(ms)), 2),
        "index_search_ms_p95": round(float(np.percentile(ms, 95)), 2),
        "recall_at_1": round(float(np.mean(r1)), 4),
        "recall_at_10": round(float(np.mean(r10)), 4),
        "rss_growth_open_mib": round(rss_open - rss0),
        "rss_after_search_mib": round(rss_search),
        "peak_rss_search_mib": round(peak_rss_mib()),
        "disk_mib": round(disk / 2**20, 1),
        "bytes_per_scan": round(disk / n),
    }


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
    if args.server:  # a server's map NAME "world", replaced
        from disco_cli.maps.milvus_address import connect, disconnect, parse_address

        address = f"{args.server.rstrip('/')}/world"
        where = parse_address(address)
        client = connect(where)
        for part in ("scans", "views", "meta"):
            client.drop_collection(f"world_{part}")
        disconnect(where, client)
    else:
        address = f"milvus:{milvus_dir}"
        shutil.rmtree(milvus_dir, ignore_errors=True)
    t = time.perf_counter()
    subprocess.run([*DISCO, "build-db", "--from", str(sqlite_map), "-o", address], check=True)
    copy_s = time.perf_counter() - t
    scans = sorted((town / "01" / "velodyne").iterdir())
    picks = np.linspace(0, len(scans) - 1, args.queries).round().astype(int)
    queries = [str(scans[i]) for i in picks]
    truth = np.loadtxt(town / "01" / "poses.txt").reshape(-1, 3, 4)[picks, :, 3]
    top1, seconds = {}, {}
    runs = (
        ("sqlite", sqlite_map, "auto"),
        ("milvus", address, "auto"),
        ("milvus_ann", address, "ann"),
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
    s.add_argument(
        "--features",
        choices=("real", "zero"),
        default="real",
        help="real: the bundled scans' feature images; zero: all-zero images of that shape",
    )
    s.add_argument("--batch", type=int, default=1000, help="scans per append")
    s.add_argument("--every", type=int, default=50_000, help="a fill progress line every N rows")
    s.add_argument("--max-fill-s", type=float, default=0.0, help="stop the fill after this long")
    s.add_argument("--min-available-gib", type=float, default=3.0, help="stop the fill below")
    s.add_argument("--search-only", action="store_true", help=argparse.SUPPRESS)
    w = sub.add_parser("world")
    w.add_argument("--queries", type=int, default=60)
    w.add_argument("--out", default="out/milvus-world")
    w.add_argument(
        "--server", default="", help="milvus://HOST:PORT: the map there (NAME world), not Lite"
    )
    args = p.parse_args()
    search = getattr(args, "search_only", False)
    print_header(f"bench_milvus {args.what}" + (" (search)" if search else ""))
    result = scale(args) if args.what == "scale" else world(args)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
