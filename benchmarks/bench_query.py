"""Query speed: search alone at 100k signatures, and streaming queries against a 10k map.

    .venv/bin/python benchmarks/bench_query.py [--model spectral] [--n-search 100000]

1. Search alone: `SignatureIndex.search` for one query at a time over N synthetic
   signatures, median per query, against a plain NumPy float64 brute force in the
   same process (the baseline), plus the memory the index holds.
2. Streaming query: a database of 10k scans (synthetic signatures and features of the
   model's shapes, written with the Database API) and 30k-point query scans on disk;
   per query: read, voxelize, embed, search, yaw of the top 10; then, with the rows
   cached, what the best one's parallax-free yaw, re-ranking wider (which every query
   against this synthetic map gets), the snap to the nearest map scan (which moves
   nearly every query's best match here) and the query's side views
   (`query_views.py`) cost, each timed against a search without it; median of each
   stage.
3. Time to the first result of `disco query` as a fresh process, by stage.
4. With a learned model: its embedding with the U-Net the CPU models use
   (`unet_numpy.py`, its convolutions in C++: `src/cpp/disco/conv3x3.cpp`), with the
   same weights in the NumPy U-Net (the BLAS path) and in torch's U-Net (one torch
   thread, as queries run), interleaved in this process, and the ratios; then the C++
   U-Net at each kernel level the CPU has (AVX-512, AVX2, plain; forced).
5. The whole match with the rows cached, with the compiled kernels and with the NumPy
   reference of the yaw searches, the re-ranking and the plain yaw (`BACKEND = "numpy"`
   of yaw_refine, verify and yaw), interleaved per query: the kernels' baseline.

Like the `disco` command, the process first asks OpenBLAS to use one thread
(`blas_threads.py`); `--process-defaults` leaves it as it is, for the ratio.

What opening a map and its integrity check cost: `benchmarks/bench_open.py`.
"""

from __future__ import annotations

import argparse
import contextlib
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _common import (
    disco_command,
    interleaved_medians_ms,
    model_arg,
    print_header,
    rss_mib,
    synthetic_scan,
)
from _common import median_of_ms as median_ms


def bench_search(n: int, dim: int, reps: int) -> dict:
    from disco_cli.query.search import SignatureIndex, brute_force_topk

    rng = np.random.default_rng(0)
    sigs = rng.random((n, dim), dtype=np.float32)
    queries = rng.random((reps, dim), dtype=np.float32)
    rss0 = rss_mib()
    t = time.perf_counter()
    index = SignatureIndex(sigs)  # takes the matrix as is: no copy
    build = time.perf_counter() - t
    del sigs
    held = rss_mib() - rss0
    ts, cpu = [], []
    for q in queries:
        t, c = time.perf_counter(), time.process_time()
        index.search(q, 10)
        ts.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    base = []
    for q in queries[: max(3, reps // 5)]:
        t = time.perf_counter()
        brute_force_topk(index.matrix, q, 10)
        base.append(time.perf_counter() - t)
    # The same answers as the baseline (the point of an exact search).
    for q in queries[:3]:
        r, _ = index.search(q, 10)
        assert (r == brute_force_topk(index.matrix, q, 10)[0]).all()
    return {
        "n": n,
        "dim": dim,
        "search_ms": median_ms(ts[2:]),
        "cpu_ms": median_ms(cpu[2:]),
        "brute_ms": median_ms(base),
        "sig_mib": n * dim * 4 / 2**20,
        "index_extra_mib": held,
        "build_s": build,
    }


def build_synthetic_db(path: Path, model, n: int) -> None:
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch

    rng = np.random.default_rng(1)
    info = ModelInfo.of(model)
    # Shapes from one real embedding, values random: search and yaw cost the same.
    # Poses: every scan within 2 m of the origin, so every candidate may take the best
    # match's place when it is snapped to the nearest map scan (the worst case: the
    # winner's yaw is refined a second time).
    bev = polar_bev_of(model, synthetic_scan(0, 2000))
    sig, feat = model.embed(bev[None])
    db = None
    for s in range(0, n, 1000):
        m = min(1000, n - s)
        batch = ScanBatch(
            [f"map/{i:06d}.bin" for i in range(s, s + m)],
            np.abs(rng.normal(size=(m, sig.shape[1]))).astype(np.float32),
            rng.random((m, *feat.shape[1:]), dtype=np.float32),
            poses=np.c_[rng.uniform(-1.4, 1.4, (m, 2)), np.zeros(m), rng.uniform(-3, 3, m)],
        )
        if db is None:
            db = Database.create(path, info, batch)
        else:
            db.append(batch)
    db.close()


def polar_bev_of(model, points: np.ndarray) -> np.ndarray:
    from disco_cli.model.bev import polar_bev

    return polar_bev(points, model.bev_config)


def bench_stream(model_name: str, n_map: int, n_queries: int, tmp: Path) -> dict:
    from disco_cli.io.readers import read_scan
    from disco_cli.maps.database import Database
    from disco_cli.model import load_model
    from disco_cli.model.yaw_refine import forget_kept_views
    from disco_cli.query.search import SignatureIndex, effective_policy, match_queries
    from disco_cli.query.verification import check_candidates

    model = load_model(model_name)
    policy = effective_policy(model)
    db_path = tmp / "map10k.db"
    build_synthetic_db(db_path, model, n_map)
    # The map's scans for the geometric check: a pool of synthetic scans on disk, read
    # back as a map's are (each row's by its id).
    pool = []
    for j in range(50):
        pool.append(tmp / f"m{j:03d}.bin")
        synthetic_scan(10_000 + j).tofile(pool[-1])

    def map_points(row):
        return read_scan(pool[row.match_id % len(pool)])

    scans = []
    for i in range(n_queries):
        p = tmp / f"q{i:04d}.bin"
        synthetic_scan(100 + i).tofile(p)
        scans.append(p)
    db = Database.open(db_path)
    ids, sigs = db.signatures()
    index = SignatureIndex(sigs)
    keys = (
        "read",
        "bev",
        "embed",
        "search",
        "yaw_rows",
        "total",
        "refine",
        "wider",
        "snap",
        "views",
        "check",
        "checked_total",
        "compiled_cached",
        "numpy_cached",
    )
    cpu = {"total": [], "embed": []}  # process CPU time: the work, apart from waiting
    stages = {k: [] for k in keys}
    # Each rule off, one at a time (`QueryPolicy`), for what it costs.
    without = {
        "refine": replace(policy, refine_yaw=0),
        "wider": replace(policy, rerank_wider=0),
        "snap": replace(policy, snap_radius=0.0),
        "views": replace(policy, view_offsets=()),
    }
    for p in scans:
        c0, t0 = time.process_time(), time.perf_counter()
        pts = read_scan(p)
        t1 = time.perf_counter()
        bev = polar_bev_of(model, pts)
        c2, t2 = time.process_time(), time.perf_counter()
        sig, feat = model.embed(bev[None])
        c3, t3 = time.process_time(), time.perf_counter()
        index.search(sig, 10)
        c4, t4 = time.process_time(), time.perf_counter()
        found = match_queries(index, ids, db, model, sig, feat, 10)[0]  # + rows + yaw
        c5, t5_first = time.process_time(), time.perf_counter()
        # The geometric check of the best rows (query/verification.py): the verified
        # query is the streaming query plus this.
        check_candidates(model, found, pts, map_points, policy.check_candidates)
        t_check = time.perf_counter() - t5_first
        cpu["total"].append((c3 - c0) + (c5 - c4))
        cpu["embed"].append(c3 - c2)
        # Costs as differences, all three with the rows now in SQLite's page cache (the
        # first call above read them cold): as above, then without the parallax-free yaw
        # of the best match, then without re-ranking wider (which every query here gets:
        # no synthetic map scan matches a query well).
        # Each repeat first forgets the query's re-centred views, which the yaw keeps
        # for the next match of the same query: a repeat then costs what a new query does.
        forget_kept_views()
        t5 = time.perf_counter()
        match_queries(index, ids, db, model, sig, feat, 10)
        forget_kept_views()
        ta = time.perf_counter()
        match_queries(index, ids, db, model, sig, feat, 10, without["refine"])
        forget_kept_views()
        tb = time.perf_counter()
        match_queries(index, ids, db, model, sig, feat, 10, without["wider"])
        forget_kept_views()
        tc = time.perf_counter()
        match_queries(index, ids, db, model, sig, feat, 10, without["snap"])
        forget_kept_views()
        td = time.perf_counter()
        match_queries(index, ids, db, model, sig, feat, 10, without["views"])
        te = time.perf_counter()
        # The same query with the NumPy reference of the yaw searches, the re-ranking
        # and the plain yaw (the compiled kernels' baseline), rows cached as for ta - t5.
        with numpy_yaw_paths():
            forget_kept_views()
            tf = time.perf_counter()
            match_queries(index, ids, db, model, sig, feat, 10)
            tg = time.perf_counter()
        for k, v in zip(
            stages,
            (
                t1 - t0,
                t2 - t1,
                t3 - t2,
                t4 - t3,
                (t5_first - t4) - (t4 - t3),
                (t3 - t0) + (t5_first - t4),
                (ta - t5) - (tb - ta),
                (ta - t5) - (tc - tb),
                (ta - t5) - (td - tc),
                (ta - t5) - (te - td),
                t_check,
                (t3 - t0) + (t5_first - t4) + t_check,
                ta - t5,
                tg - tf,
            ),
        ):
            stages[k].append(v)
    db.close()
    out = {k: median_ms(v[2:]) for k, v in stages.items()}
    out |= {f"cpu_{k}": median_ms(v[2:]) for k, v in cpu.items()}
    return out | {"db": str(db_path), "scan": str(scans[0])}


@contextlib.contextmanager
def numpy_yaw_paths():
    """The yaw searches, the re-ranking's correlations and the plain yaw on their NumPy
    reference paths (`BACKEND = "numpy"` of yaw_refine, verify and yaw) while inside."""
    from disco_cli.model import verify, yaw, yaw_refine

    modules = (verify, yaw, yaw_refine)
    before = [m.BACKEND for m in modules]
    for m in modules:
        m.BACKEND = "numpy"
    try:
        yield
    finally:
        for m, b in zip(modules, before):
            m.BACKEND = b


def bench_embed(model_name: str, rounds: int = 10) -> dict | None:
    """Embedding one scan with the model as loaded (the U-Net's convolutions in C++),
    with the same weights in the NumPy U-Net (`backend="numpy"`) and in torch's U-Net
    on one thread, interleaved; then the C++ U-Net at each kernel level the CPU has
    (forced through the level cap), and at the level in use with the direct
    convolution only vs Winograd where the core chooses it. None for a model without
    a U-Net."""
    from disco_cli import _core
    from disco_cli.model import load_model
    from disco_cli.model.checkpoint import read_checkpoint
    from disco_cli.model.disco import DiscoModel, build_net, to_numpy
    from disco_cli.model.unet_numpy import FrozenUNet

    model = load_model(model_name)
    if not getattr(model, "frozen", False):
        return None
    import torch

    path = Path(model_name) if Path(model_name).is_file() else None
    if path is None:
        from disco_cli.model import DEFAULT_WEIGHTS

        path = DEFAULT_WEIGHTS
    ckpt = read_checkpoint(path)
    net = build_net(ckpt["model_config"])
    net.load_state_dict(ckpt["state_dict"])
    ref = DiscoModel(net, model.bev_config, model.model_config)
    state = {k: to_numpy(v) for k, v in ckpt["state_dict"].items()}
    numpy_net = FrozenUNet(state, model.model_config, backend="numpy")
    plain = DiscoModel(numpy_net, model.bev_config, model.model_config, state=state)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    bevs = [polar_bev_of(model, synthetic_scan(200 + i))[None] for i in range(4)]
    it = iter(range(10**9))
    levels = {n: lv for lv in (3, 2, 0) if (n := _core._conv3x3_kernel_name(lv))}
    cap = _core._set_bev_kernel_level(3)  # the best kernel for the comparison; put back after

    def at_level(level: int):
        def run():
            _core._set_bev_kernel_level(level)
            model.features(bevs[next(it) % 4])

        return run

    def with_algorithm(algorithm: str):
        def run():
            model.net.set_conv_algorithm(algorithm)
            model.features(bevs[next(it) % 4])

        return run

    fns = {
        "cpp": lambda: model.embed(bevs[next(it) % 4]),
        "numpy": lambda: plain.embed(bevs[next(it) % 4]),
        "torch": lambda: ref.embed(bevs[next(it) % 4]),
        "cu": lambda: model.features(bevs[next(it) % 4]),
        "nu": lambda: plain.features(bevs[next(it) % 4]),
        "tu": lambda: ref.features(bevs[next(it) % 4]),
    }
    try:
        t = interleaved_medians_ms(fns, rounds, block=5)
        by_level = interleaved_medians_ms(
            {name: at_level(lv) for name, lv in levels.items()}, rounds, block=5
        )
        _core._set_bev_kernel_level(cap)
        algo = interleaved_medians_ms(
            {"direct": with_algorithm("direct"), "auto": with_algorithm("auto")}, 2 * rounds, 5
        )
        model.net.set_conv_algorithm("direct")
        sig_direct, _ = model.embed(bevs[0])
    finally:
        model.net.set_conv_algorithm("auto")
        _core._set_bev_kernel_level(cap)
        torch.set_num_threads(threads)
    sig_t, _ = ref.embed(bevs[0])
    sig_c, _ = model.embed(bevs[0])
    sig_n, _ = plain.embed(bevs[0])
    return t | {
        "kernel": _core._conv3x3_kernel_name(),
        "levels": by_level,
        "algorithms": algo,
        "sig_diff_direct": float(np.abs(sig_direct - sig_t).max()),
        "sig_diff": float(np.abs(sig_c - sig_t).max()),
        "sig_diff_numpy": float(np.abs(sig_n - sig_t).max()),
    }


def bench_first_result(db: str, scan: str, model: str) -> dict:
    """Wall time of a fresh `disco query` process, and how it splits (from -X importtime
    is too fine; instead time the phases in a fresh interpreter)."""
    exe = disco_command()
    t = time.perf_counter()
    subprocess.run(
        [*exe, "query", scan, "--db", db, "--format", "tsv", "--model", model],
        check=True,
        capture_output=True,
    )
    total = time.perf_counter() - t
    code = f"""
import time; t0 = time.perf_counter()
import disco_cli.cli; t1 = time.perf_counter()
import numpy; from disco_cli.model import load_model; from disco_cli.maps.database import Database
from disco_cli.query.search import SignatureIndex, match_queries
from disco_cli.embedding.load import load_bev
t2 = time.perf_counter()
db = Database.open({db!r}); m = load_model({model!r}); t3 = time.perf_counter()
ids, s = db.signatures(); ix = SignatureIndex(s); t4 = time.perf_counter()
sig, f = m.embed(load_bev({scan!r}, m.bev_config)[None]); match_queries(ix, ids, db, m, sig, f, 10)
t5 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)
"""
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    interp = time.perf_counter() - t
    cli, imports, model, sigs, first = (float(v) for v in out.stdout.split())
    startup = interp - (cli + imports + model + sigs + first)
    return {
        "total_ms": total * 1e3,
        "python_ms": startup * 1e3,
        "cli_import_ms": cli * 1e3,
        "imports_ms": imports * 1e3,
        "model_ms": model * 1e3,
        "signatures_ms": sigs * 1e3,
        "first_query_ms": first * 1e3,
    }


def bench_memory(model_name: str, n: int, tmp: Path) -> dict:
    """Peak RSS of `disco query` (one query, fresh process) against n scans vs 100 scans."""
    from disco_cli.model import load_model

    model = load_model(model_name)
    scan = tmp / "mq.bin"
    synthetic_scan(7).tofile(scan)
    exe = disco_command()
    out = {}
    for rows in (100, n):
        db = tmp / f"mem{rows}.db"
        build_synthetic_db(db, model, rows)
        code = (
            "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, "
            "stdout=subprocess.DEVNULL); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
        )
        t = time.perf_counter()
        res = subprocess.run(
            [
                sys.executable,
                "-c",
                code,
                *exe,
                "query",
                str(scan),
                "--db",
                str(db),
                "--model",
                model_name,
            ],
            capture_output=True,
            text=True,
            check=True,
        )
        out[f"wall{rows}"] = time.perf_counter() - t
        out[rows] = int(res.stdout.split()[-1]) / 1024
        out[f"size{rows}"] = db.stat().st_size / 2**20
        sig_dim = 1024
        db.unlink()
    out["sig_mib"] = n * sig_dim * 4 / 2**20
    return out


def bench_yaw_f16(
    model_name: str, map_dir: Path, query_dir: Path, tmp: Path, radius: float = 5.0
) -> dict:
    """Yaw from features stored as float16 (through a real database) vs float32, on
    revisits: each query scan with its nearest map scan within `radius` m (poses.txt)."""
    from disco_cli.io.poses import read_kitti_poses, wrap_deg, xy_yaw
    from disco_cli.io.readers import list_scans, read_scan
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch
    from disco_cli.model import load_model
    from disco_cli.model.bev import polar_bev

    model = load_model(model_name)

    def embed(folder: Path) -> tuple[list[Path], np.ndarray, np.ndarray, np.ndarray]:
        paths = list_scans(folder)
        sig, feat = model.embed(
            np.stack([polar_bev(read_scan(p), model.bev_config) for p in paths])
        )
        return paths, sig, feat, read_kitti_poses(folder / "poses.txt")

    m_paths, m_sig, m_feat, m_pose = embed(map_dir)
    q_paths, _, q_feat, q_pose = embed(query_dir)
    db = Database.create(
        tmp / "yaw.db", ModelInfo.of(model), ScanBatch([str(p) for p in m_paths], m_sig, m_feat)
    )
    ids, _ = db.signatures()
    m_feat16 = db.rows(ids).features
    db.close()
    mx, my, myaw = xy_yaw(m_pose)
    qx, qy, qyaw = xy_yaw(q_pose)
    diffs, err32, err16 = [], [], []
    for i in range(len(q_paths)):
        d = np.hypot(mx - qx[i], my - qy[i])
        j = int(np.argmin(d))
        if d[j] > radius:
            continue
        truth = wrap_deg(np.degrees(qyaw[i] - myaw[j]))
        y32 = float(model.yaw(q_feat[i], m_feat[j : j + 1])[0])
        y16 = float(model.yaw(q_feat[i], m_feat16[j : j + 1])[0])
        diffs.append(abs(wrap_deg(y16 - y32)))
        err32.append(abs(wrap_deg(y32 - truth)))
        err16.append(abs(wrap_deg(y16 - truth)))
    diffs = np.asarray(diffs)
    return {
        "pairs": len(diffs),
        "max_diff": float(diffs.max()),
        "mean_diff": float(diffs.mean()),
        "changed": int(np.count_nonzero(diffs > 1e-3)),
        "err32": float(np.median(err32)),
        "err16": float(np.median(err16)),
        "mean32": float(np.mean(err32)),
        "mean16": float(np.mean(err16)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="spectral")
    ap.add_argument("--n-search", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=1024)
    ap.add_argument("--n-map", type=int, default=10_000)
    ap.add_argument("--queries", type=int, default=30)
    ap.add_argument(
        "--memory",
        type=int,
        default=0,
        help="also measure the peak RSS of `disco query` against this many scans",
    )
    ap.add_argument(
        "--yaw-f16",
        nargs=2,
        type=Path,
        metavar=("MAP_DIR", "QUERY_DIR"),
        help="only measure the yaw cost of float16 features on two sessions",
    )
    ap.add_argument(
        "--process-defaults",
        action="store_true",
        help="leave OpenBLAS's threads as they are (disco sets one)",
    )
    args = ap.parse_args()
    if not args.process_defaults:
        from disco_cli.runtime.blas_threads import one_blas_thread_for_process

        one_blas_thread_for_process()
    print_header("bench_query")
    print(f"  OpenBLAS runs one thread (as `disco` sets it): {not args.process_defaults}")
    if args.yaw_f16:
        with tempfile.TemporaryDirectory() as tmp:
            y = bench_yaw_f16(args.model, *args.yaw_f16, Path(tmp))
        print(
            f"yaw from float16 vs float32 features ({args.model}), {y['pairs']} revisit pairs: "
            f"|difference| mean {y['mean_diff']:.4f}, max {y['max_diff']:.4f} deg, "
            f"{y['changed']} pairs changed by > 0.001 deg; |error| vs ground truth: median "
            f"{y['err32']:.3f} (float32) / {y['err16']:.3f} (float16), mean {y['mean32']:.3f} "
            f"/ {y['mean16']:.3f} deg"
        )
        return

    for n in (10_000, args.n_search):
        r = bench_search(n, args.dim, 30)
        print(
            f"search alone, random signatures, {r['n']} x {r['dim']} float32 "
            f"({r['sig_mib']:.0f} MiB): {r['search_ms']:.2f} ms/query (median; CPU time of all "
            f"threads {r['cpu_ms']:.2f} ms), NumPy brute "
            f"force {r['brute_ms']:.1f} ms ({r['brute_ms'] / r['search_ms']:.1f}x); index "
            f"built in {r['build_s']:.2f} s and holds +{r['index_extra_mib']:.1f} MiB beyond "
            "the signature matrix"
        )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"  peak RSS of this process so far: {peak:.0f} MiB")

    with tempfile.TemporaryDirectory() as tmp:
        # `default` without shipped weights: the same architecture, untrained (same cost).
        model, what = model_arg(args.model, Path(tmp))
        s = bench_stream(model, args.n_map, args.queries, Path(tmp))
        print(
            f"streaming query vs {args.n_map} scans ({what}): total {s['total']:.2f} "
            "ms/query"
            f" = read {s['read']:.2f} + voxelize {s['bev']:.2f} + embed {s['embed']:.2f} + "
            f"search {s['search']:.2f} + rows, re-ranking and yaw {s['yaw_rows']:.2f} (medians); "
            f"of the latter, the parallax-free yaw of the best match {s['refine']:.2f} (beyond "
            "the snap's, which finds it on the way), "
            f"re-ranking down to 40 where none of the 10 matches well {s['wider']:.2f} (every "
            f"query here), the snap to the nearest map scan {s['snap']:.2f} (here it moves "
            "nearly every query's best match; the yaw to the scan it moves to follows from "
            f"the two map poses) and the query's side views {s['views']:.2f} (their search "
            "and re-ranking); "
            f"process CPU time per query {s['cpu_total']:.2f} ms, of the embed "
            f"{s['cpu_embed']:.2f} ms (medians)"
        )
        print(
            f"verified query (the default: the streaming query, then the layout check of "
            f"the best 3 rows, their scans read from disk): {s['checked_total']:.2f} ms/query "
            f"= {s['checked_total'] / s['total']:.2f}x the streaming query; the check "
            f"{s['check']:.2f} ms (medians, same queries)"
        )
        print(
            f"the whole match (search, rows, re-ranking and yaw; rows cached): "
            f"{s['compiled_cached']:.2f} ms with "
            f"the compiled kernels vs {s['numpy_cached']:.2f} ms with the NumPy reference of "
            "the yaw searches, the re-ranking and the plain yaw "
            f"({s['numpy_cached'] / s['compiled_cached']:.2f}x; interleaved, medians)"
        )
        e = bench_embed(model)
        if e is not None:
            print(
                f"embed one scan ({what}), interleaved medians: {e['cpp']:.2f} ms with the "
                f"C++ U-Net ({e['kernel']} kernel) vs {e['numpy']:.2f} ms with the NumPy "
                f"U-Net ({e['numpy'] / e['cpp']:.2f}x) vs {e['torch']:.2f} ms with torch's on "
                f"one thread ({e['torch'] / e['cpp']:.2f}x); the U-Net alone {e['cu']:.2f} vs "
                f"{e['nu']:.2f} vs {e['tu']:.2f} ms ({e['nu'] / e['cu']:.2f}x, "
                f"{e['tu'] / e['cu']:.2f}x); signatures differ from torch's by at most "
                f"{e['sig_diff']:.1e} (C++) and {e['sig_diff_numpy']:.1e} (NumPy)"
            )
            print(
                "the C++ U-Net by kernel level (forced), interleaved medians: "
                + ", ".join(f"{name} {ms:.2f} ms" for name, ms in e["levels"].items())
            )
            a = e["algorithms"]
            print(
                f"the C++ U-Net ({e['kernel']} kernel) with the direct convolution only "
                f"{a['direct']:.3f} ms vs Winograd where chosen {a['auto']:.3f} ms "
                f"({a['direct'] / a['auto']:.2f}x; interleaved medians); signatures differ "
                f"from torch's by at most {e['sig_diff_direct']:.1e} (direct only) and "
                f"{e['sig_diff']:.1e} (with Winograd)"
            )
        f = bench_first_result(s["db"], s["scan"], model)
        print(
            f"first result of a fresh `disco query` process: {f['total_ms']:.0f} ms; a fresh "
            f"interpreter spends: python {f['python_ms']:.0f}, cli import "
            f"{f['cli_import_ms']:.0f}, "
            f"numpy/model/db imports {f['imports_ms']:.0f}, open db + load model "
            f"{f['model_ms']:.0f}, read {args.n_map} signatures + index "
            f"{f['signatures_ms']:.0f}, "
            f"first query {f['first_query_ms']:.0f} ms"
        )
        if args.memory:
            m = bench_memory(model, args.memory, Path(tmp))
            print(
                f"peak RSS of `disco query` (one query): {m[100]:.0f} MiB against 100 scans, "
                f"{m[args.memory]:.0f} MiB against {args.memory} scans "
                f"({m[f'size{args.memory}']:.0f} MiB on disk); the difference "
                f"{m[args.memory] - m[100]:.0f} MiB = "
                f"{(m[args.memory] - m[100]) / m['sig_mib']:.2f}x the {m['sig_mib']:.0f} MiB "
                f"of signatures; that process ran {m[f'wall{args.memory}']:.1f} s (vs "
                f"{m['wall100']:.1f} s against 100 scans)"
            )


if __name__ == "__main__":
    main()
