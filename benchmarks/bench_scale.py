"""A map of a million scans on one machine: the approximate index against the exact one.

    PYTHONPATH=src:SITE .venv/bin/python benchmarks/bench_scale.py --n 1000000
        [--queries 500] [--nprobe 256 512] [--k-factor 10] [--out out/scale]

(faiss from `pip install 'disco-cli[ann]'`.) The signatures are realistic, not uniform
random: six towns of held-out styles (seeds 8101-8106, 400 scans 1 m apart per session)
are simulated and embedded by the default network, once (cached under --out). Their
2,400 map scans are the first rows; the other N - 2,400 rows are new places made from
them: a point on one town's route (between two consecutive scans, which lie 0.2 apart in
signature space) mixed with up to 50 % of a point on another's, plus noise of 5 % of
each dimension's spread, renormalized. So the map is clustered along routes as a
fleet's map is, and it holds near-twins of the real places that a query must get past.
The queries are the towns' second sessions (driven back in another lane after 30 % of
the objects changed): real queries of places the map holds.

Measured, with the exact `SignatureIndex` (one thread) as the baseline of the same run:

- search: median ms per query on one thread; for the approximate index in a fresh
  process that loads the sidecar (`map.db.ann`) as `disco query` does;
- memory: the resident growth (RSS) of building the exact index (plus its float32
  matrix, which it holds) and of loading the sidecar;
- recall@1 / @10 of the approximate search against the exact top 1 / top 10;
- pipeline R@1: the whole query (re-ranking by feature correlation, the wider pass and
  the snap, as `disco query`) with each index; a match is true within 5 m in the query's
  own town (a generated row stands for the map scan it was mostly made from);
- build: seconds to train and fill the approximate index (--build-threads, 2);
- map: bytes per scan of a map file holding one town's 400 scans (`Database.create`,
  the writer of `disco build-db`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import REPO, print_header, rss_mib

SEEDS = {
    "industrial": 8101,
    "park": 8102,
    "parking": 8103,
    "terrace": 8104,
    "suburban": 8105,
    "grid": 8106,
}
RADIUS = 5.0
TOWN_SPACING = 1e5  # towns laid side by side in x, so no match crosses between them


def towns(out: Path, model) -> list[dict]:
    """Each town's embedded map and query session (simulated and embedded once)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    import ood_suite as S

    found = []
    for style, seed in SEEDS.items():
        folder = out / "worlds" / f"{style}-{seed}"
        if not (folder / "world.json").is_file():
            cmd = [sys.executable, "-m", "disco_cli.cli", "simulate", str(folder)]
            cmd += ["--sessions", "2", "--length-m", "400", "--sensor", "hdl32"]
            cmd += ["--seed", str(seed), "--threads", "2", "--change", "0.3"]
            cmd += ["--style", style, "--robot-offset", "1.5"]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        cache = folder / f"emb-{model.fingerprint[:12]}.npz"
        if not cache.is_file():
            e = S.embed_world(model, folder, threads=2)
            np.savez(
                cache,
                ms=e.map_signatures,
                mf=e.map_features,
                mp=e.map_poses,
                qs=e.query_signatures,
                qf=e.query_features,
                qp=e.queries.poses,
            )
        found.append(dict(np.load(cache)))
    return found


def generate(routes: list[np.ndarray], n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """`n` new places mixed from points on the routes (module docstring), and for each
    the route row it was mostly made from (rows counted over all routes in order)."""
    rng = np.random.default_rng(seed)
    lens = np.array([len(r) for r in routes])
    every = np.concatenate(routes).astype(np.float32)
    start = np.r_[0, np.cumsum(lens)[:-1]]
    spread = every.std(axis=0)
    out = np.empty((n, every.shape[1]), np.float32)
    base = np.empty(n, np.int64)
    for s in range(0, n, 65536):
        m = min(65536, n - s)

        def on_route() -> tuple[np.ndarray, np.ndarray]:
            town = rng.integers(0, len(routes), m)
            at = rng.uniform(0, lens[town] - 1)
            a = start[town] + np.floor(at).astype(np.int64)
            t = (at - np.floor(at))[:, None].astype(np.float32)
            return (1 - t) * every[a] + t * every[a + 1], a + np.round(t[:, 0]).astype(np.int64)

        first, row = on_route()
        second, _ = on_route()
        mix = rng.uniform(0.0, 0.5, (m, 1)).astype(np.float32)
        v = (1 - mix) * first + mix * second
        v += 0.05 * spread * rng.standard_normal(v.shape, dtype=np.float32)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        out[s : s + m], base[s : s + m] = v, row
    return out, base


class _Rows:
    """The map's rows for `match_queries`: a generated row answers with the features
    and pose of the map scan it was made from."""

    def __init__(self, base: np.ndarray, feats: np.ndarray, pose4: np.ndarray):
        self.base, self.feats, self.pose4 = base, feats, pose4

    def rows(self, ids):
        from disco_cli.maps.database import MatchRows

        ids = np.asarray(ids, np.int64)
        b = self.base[ids]
        return MatchRows(ids, [str(i) for i in ids], self.pose4[b], self.feats[b])


def pipeline_r1(index, n, rows: _Rows, model, qs, qf, q_xy, has) -> float:
    from disco_cli.query.search import match_queries

    found = match_queries(index, np.arange(n), rows, model, qs, qf, 1)
    hit = []
    for i, m in enumerate(found):
        if has[i]:
            xy = rows.pose4[rows.base[m[0].row], :2] if m else np.array([np.inf, np.inf])
            hit.append(bool(np.hypot(*(xy - q_xy[i])) <= RADIUS))
    return float(np.mean(hit))


_LOADER = """
import json, sys, time, numpy as np, faiss
faiss.omp_set_num_threads(1)
from disco_cli.maps.index.ann import AnnIndex
def rss():
    for l in open('/proc/self/status'):
        if l.startswith('VmRSS:'): return int(l.split()[1]) / 1024
path, qfile, key = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
kf, probes = int(sys.argv[4]), [int(v) for v in sys.argv[5:]]
q = np.load(qfile); r0 = rss(); t = time.perf_counter()
index, ids, _ = AnnIndex.load(path, key)
load_s = time.perf_counter() - t; r1 = rss()
out = {"rss_mib": r1 - r0, "load_s": load_s, "runs": []}
for nprobe in probes:
    index.set_search(nprobe, kf)
    for v in q[:20]: index.search(v, 10)
    ts, rows = [], []
    for v in q:
        t = time.perf_counter(); r, _ = index.search(v, 10); ts.append(time.perf_counter() - t)
        rows.append(r.tolist())
    out["runs"].append({"nprobe": nprobe, "ms": float(np.median(ts)) * 1e3, "rows": rows})
print(json.dumps(out))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000, help="map rows")
    ap.add_argument("--queries", type=int, default=500)
    ap.add_argument("--nprobe", type=int, nargs="+", help="clusters scanned (default: the index's)")
    ap.add_argument("--k-factor", type=int, default=10)
    ap.add_argument("--out", type=Path, default=REPO / "out" / "scale")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--build-threads", type=int, default=2, help="threads that build the index")
    ap.add_argument(
        "--save-signatures",
        type=Path,
        help="also write the towns' signatures (map and query sessions) to this .npz",
    )
    ap.add_argument(
        "--signatures",
        type=Path,
        help="take the towns' signatures from a --save-signatures file instead of "
        "simulating and embedding (no features there: no pipeline R@1, no map size)",
    )
    args = ap.parse_args()
    if args.signatures is None:
        print_header("bench_scale")
    else:  # a machine without the compiled core (it only names the BEV kernel)
        from _common import cpu_model

        print(f"# bench_scale on machine: {cpu_model()}, {os.cpu_count()} cores", flush=True)

    import torch

    from disco_cli.io.poses import xy_yaw
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch
    from disco_cli.maps.index.ann import AnnIndex, default_params
    from disco_cli.model import load_model
    from disco_cli.query.search import SignatureIndex

    torch.set_num_threads(2)
    model = load_model("default")
    if args.signatures is not None:
        with np.load(args.signatures) as f:
            data = [
                {"ms": f[f"ms{k}"], "qs": f[f"qs{k}"], "mp": f[f"mp{k}"], "qp": f[f"qp{k}"]}
                for k in range(int(f["towns"]))
            ]
    else:
        data = towns(args.out, model)
    if args.save_signatures is not None:
        keep = {"towns": len(data)}
        for k, t in enumerate(data):
            keep |= {f"{a}{k}": t[a] for a in ("ms", "qs", "mp", "qp")}
        np.savez_compressed(args.save_signatures, **keep)
    with_features = "mf" in data[0]
    routes = [t["ms"] for t in data]
    n_real = sum(len(r) for r in routes)
    if args.n < n_real:
        raise SystemExit(f"--n must be at least the {n_real} real map scans")
    t0 = time.perf_counter()
    made, made_base = generate(routes, args.n - n_real, args.seed)
    sigs = np.concatenate([np.concatenate(routes), made])
    del made
    base = np.concatenate([np.arange(n_real), made_base])
    gen_s = time.perf_counter() - t0

    # Each town's poses, moved TOWN_SPACING apart in x; queries alike.
    pose4, q_xy, qs, qf = [], [], [], []
    for k, t in enumerate(data):
        mx, my, myaw = xy_yaw(t["mp"])
        pose4.append(np.c_[mx + k * TOWN_SPACING, my, t["mp"][:, 2, 3], myaw])
        qx, qy, _ = xy_yaw(t["qp"])
        q_xy.append(np.c_[qx + k * TOWN_SPACING, qy])
        qs.append(t["qs"])
        qf.append(t["qf"] if with_features else np.zeros((len(t["qs"]), 1), np.float32))
    pose4, q_xy = np.concatenate(pose4), np.concatenate(q_xy)
    qs, qf = np.concatenate(qs), np.concatenate(qf)
    pick = np.random.default_rng(args.seed + 1).choice(
        len(qs), min(args.queries, len(qs)), replace=False
    )
    qs, qf, q_xy = qs[pick], qf[pick], q_xy[pick]
    near = np.hypot(*(pose4[None, :, :2] - q_xy[:, None]).transpose(2, 0, 1)).min(axis=1)
    has = near <= RADIUS
    rows = _Rows(base, np.concatenate([t["mf"] for t in data]), pose4) if with_features else None

    # The exact baseline, one thread (the int8 pre-scan runs from 4,096 rows).
    r0 = rss_mib()
    t0 = time.perf_counter()
    exact = SignatureIndex(sigs, threads=1)
    exact_build = time.perf_counter() - t0
    exact_mib = rss_mib() - r0 + sigs.nbytes / 2**20
    exact.search(qs[:5], 10)
    ts, truth = [], []
    for q in qs:
        t = time.perf_counter()
        r, _ = exact.search(q, 10)
        ts.append(time.perf_counter() - t)
        truth.append(r)
    truth = np.array(truth)
    exact_ms = float(np.median(ts)) * 1e3
    exact_r1 = pipeline_r1(exact, args.n, rows, model, qs, qf, q_xy, has) if rows else None
    del exact

    import faiss

    faiss.omp_set_num_threads(args.build_threads)
    params = default_params(args.n, sigs.shape[1])
    t0 = time.perf_counter()
    ann = AnnIndex.build(sigs, params)
    build_s = time.perf_counter() - t0
    del sigs
    key = {"bench": args.n, "seed": args.seed}
    args.out.mkdir(parents=True, exist_ok=True)
    side = args.out / f"bench-{args.n}.ann"
    ann.save(side, key, np.arange(args.n), None)
    probes = args.nprobe or [params.nprobe]
    with tempfile.TemporaryDirectory() as tmp:
        qfile = Path(tmp) / "q.npy"
        np.save(qfile, qs)
        proc = subprocess.run(
            [sys.executable, "-c", _LOADER, str(side), str(qfile), json.dumps(key)]
            + [str(args.k_factor)]
            + [str(p) for p in probes],
            capture_output=True,
            text=True,
            check=True,
        )
        loaded = json.loads(proc.stdout)

        # Bytes per scan of a real map file: one town, as build-db writes it.
        per_scan = None
        if with_features:
            t = data[0]
            mx, my, myaw = xy_yaw(t["mp"])
            db = Database.create(
                Path(tmp) / "map.db",
                ModelInfo.of(model),
                ScanBatch(
                    [f"scan{i:06d}.bin" for i in range(len(t["ms"]))],
                    t["ms"],
                    t["mf"],
                    np.c_[mx, my, t["mp"][:, 2, 3], myaw],
                ),
            )
            with db:
                per_scan = db.size_bytes() / len(db)

    print(
        f"n={args.n} rows ({n_real} real, generated in {gen_s:.0f} s); "
        f"{len(qs)} queries ({int(has.sum())} with a map scan within {RADIUS:g} m); "
        f"index {params}",
        flush=True,
    )
    for run in loaded["runs"]:
        got = np.array(run["rows"])
        r1 = float(np.mean(got[:, 0] == truth[:, 0]))
        r10 = float(np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, truth)]))
        ann.set_search(run["nprobe"], args.k_factor)
        faiss.omp_set_num_threads(1)
        pipeline = "no pipeline R@1 (no features)"
        if rows is not None:
            ann_r1 = pipeline_r1(ann, args.n, rows, model, qs, qf, q_xy, has)
            pipeline = f"pipeline R@1 {ann_r1:.4f} (exact {exact_r1:.4f})"
        map_size = "" if per_scan is None else f", map {per_scan / 1024:.1f} KiB/scan"
        print(
            f"nprobe {run['nprobe']}: search {run['ms']:.2f} ms (exact {exact_ms:.2f} ms, "
            f"x{exact_ms / run['ms']:.1f}), memory {loaded['rss_mib']:.0f} MiB "
            f"(exact {exact_mib:.0f} MiB), recall@1 {r1:.4f} recall@10 {r10:.4f}, "
            f"{pipeline}, build {build_s:.0f} s (exact {exact_build:.1f} s), "
            f"load {loaded['load_s']:.1f} s, sidecar {side.stat().st_size / args.n:.0f} B/scan"
            f"{map_size}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
