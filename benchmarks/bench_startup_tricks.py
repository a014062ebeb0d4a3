"""What each process-level trick of a query still buys (issue 32), each against its absence.

    .venv/bin/python benchmarks/bench_startup_tricks.py [--rounds 7] [--queries 15]

1. The FFT (`model/fft.py` loads SciPy's compiled pocketfft by file path instead of
   `import scipy.fft`): in fresh processes, interleaved, the time to load it either
   way, and a whole one-scan `disco query` (the 26 sample scans as the map) as shipped
   and with `scipy.fft` imported first (then model/fft.py takes SciPy's public path).
2. glibc keeping freed memory (mallopt: mmap threshold 32 MiB, no trimming; `disco`
   made these settings until issue 32 measured them here and removed them): the
   worst-case query against 10,000 synthetic scans (read, voxelize, embed, search,
   re-rank 40, snap, yaw; as `bench_query.py`) in fresh processes, alternately with and
   without it; median per query of each process, then the median over processes.
3. OpenBLAS on one thread around the U-Net (`blas_threads.blas_threads`): one BEV's
   embedding, interleaved in one process with and without the block, (a) in a program
   that imported NumPy first (OpenBLAS starts one thread per core) and (b) as `disco`
   runs (`set_threads` before NumPy loads: OpenBLAS starts with one thread).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import REPO, disco_command, print_header

PY = sys.executable

_LOAD_FFT = """
import time, numpy
t = time.perf_counter()
{what}
print(time.perf_counter() - t)
"""

_QUERY_CLI = """
import sys
{pre}
from disco_cli.cli import main
sys.argv = ["disco", "query", sys.argv[1], "--db", sys.argv[2], "--format", "tsv"]
main()
"""

_STREAM = """
import sys, time
sys.path.insert(0, sys.argv[3])
if sys.argv[2] == "1":  # M_MMAP_THRESHOLD (-3) 32 MiB, M_TRIM_THRESHOLD (-1) never
    import ctypes
    mallopt = ctypes.CDLL("libc.so.6").mallopt
    mallopt(-3, 32 << 20)
    mallopt(-1, 2**31 - 1)
from disco_cli.runtime.threads import set_threads
set_threads(1)
import numpy as np
from bench_query import polar_bev_of
from _common import synthetic_scan
from disco_cli.maps.database import Database
from disco_cli.model import load_model
from disco_cli.query.search import SignatureIndex, match_queries
model = load_model("default")
db = Database.open(sys.argv[1])
ids, sigs = db.signatures()
index = SignatureIndex(sigs)
wall, cpu = [], []
for i in range(int(sys.argv[4])):
    pts = synthetic_scan(100 + i)
    t, c = time.perf_counter(), time.process_time()
    sig, feat = model.embed(polar_bev_of(model, pts)[None])
    match_queries(index, ids, db, model, sig, feat, 10)
    wall.append(time.perf_counter() - t)
    cpu.append(time.process_time() - c)
# The first two warm up; the first alone is what a one-scan query pays.
print(float(np.median(wall[2:])), float(np.median(cpu[2:])), cpu[0])
"""

_BLAS = """
import sys, time, contextlib
if sys.argv[1] == "disco":
    from disco_cli.runtime.threads import set_threads
    set_threads(1)
import numpy as np
import disco_cli.model.disco as dm
from disco_cli.model import load_model
model = load_model("default")
bev = np.random.default_rng(0).random((1, *model.bev_config.shape), dtype=np.float32)
shipped = dm.blas_threads
none = lambda n=1: contextlib.nullcontext()
times = {"with": [], "without": []}
for r in range(int(sys.argv[2])):
    for name, ctx in (("with", shipped), ("without", none)):
        dm.blas_threads = ctx
        for _ in range(5):
            t = time.perf_counter()
            model.embed(bev)
            times[name].append(time.perf_counter() - t)
print(statistics.median(times["with"]), statistics.median(times["without"]))
""".replace("import sys,", "import statistics, sys,")


def _run(code: str, *args: str) -> tuple[float, str]:
    t = time.perf_counter()
    out = subprocess.run(
        [PY, "-c", code, *args], capture_output=True, text=True, check=True, cwd=REPO
    ).stdout
    return time.perf_counter() - t, out


def bench_fft(rounds: int, map_db: Path, scan: Path) -> dict:
    loads = {"file path": [], "import scipy.fft": []}
    whole = {"shipped": [], "scipy.fft first": []}
    what = {
        "file path": "from disco_cli.model import fft; fft.backend()",
        "import scipy.fft": "import scipy.fft",
    }
    pre = {"shipped": "", "scipy.fft first": "import scipy.fft"}
    for _ in range(rounds):
        for name, code in what.items():
            loads[name].append(float(_run(_LOAD_FFT.format(what=code))[1]))
        for name, code in pre.items():
            whole[name].append(_run(_QUERY_CLI.format(pre=code), str(scan), str(map_db))[0])
    med = lambda v: 1e3 * statistics.median(v)  # noqa: E731
    return {k: med(v) for k, v in {**loads, **whole}.items()}


def bench_numpy_fft(rounds: int) -> dict:
    """NumPy's own FFT against the pocketfft loaded here, on one query's re-ranking
    spectra (40 candidates' 40 x 120 images, float32), interleaved in this process."""
    import numpy as np
    from _common import interleaved_medians_ms

    from disco_cli.model import fft

    x = np.random.default_rng(0).random((40, 40, 120), dtype=np.float32)
    fns = {"pocketfft": lambda: fft.rfft(x, axis=-1), "numpy": lambda: np.fft.rfft(x, axis=-1)}
    return interleaved_medians_ms(fns, rounds)


def bench_malloc(rounds: int, queries: int, tmp: Path) -> dict:
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_query import build_synthetic_db

    from disco_cli.model import load_model

    db = tmp / "map10k.db"
    build_synthetic_db(db, load_model("default"), 10_000)
    out: dict[str, list[list[float]]] = {"keeping freed memory": [], "as it is": []}
    for _ in range(rounds):
        for name, flag in (("keeping freed memory", "1"), ("as it is", "0")):
            args = (str(db), flag, str(REPO / "benchmarks"), str(queries))
            out[name].append([float(v) for v in _run(_STREAM, *args)[1].split()])
    # Per setting: medians over processes of (wall, CPU, first query's CPU), ms.
    return {k: [1e3 * statistics.median(col) for col in zip(*v)] for k, v in out.items()}


def bench_blas(rounds: int) -> dict:
    out = {}
    for how in ("numpy first", "disco"):
        w, wo = map(float, _run(_BLAS, how, str(rounds))[1].split())
        out[how] = (1e3 * w, 1e3 * wo)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--queries", type=int, default=15, help="queries per stream process")
    ap.add_argument("--skip", nargs="*", default=[], choices=["fft", "malloc", "blas"])
    args = ap.parse_args()
    print_header("bench_startup_tricks")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if "fft" not in args.skip:
            db = tmp / "samples.db"
            samples = REPO / "data" / "samples"
            cmd = [*disco_command(), "build-db", str(samples / "00"), "-o", str(db), "-q"]
            subprocess.run(cmd, check=True, capture_output=True)
            scan = sorted((samples / "01" / "velodyne").glob("*.bin"))[3]
            f = bench_fft(args.rounds, db, scan)
            n = bench_numpy_fft(args.rounds)
            print(
                f"FFT: loading pocketfft by file path {f['file path']:.0f} ms, import scipy.fft "
                f"{f['import scipy.fft']:.0f} ms; a whole one-scan disco query "
                f"{f['shipped']:.0f} ms as shipped, {f['scipy.fft first']:.0f} ms with "
                f"scipy.fft imported first (medians of {args.rounds} fresh processes each); "
                f"rfft of 40 x 40 x 120 float32: {1e3 * n['pocketfft']:.0f} us, NumPy's own "
                f"{1e3 * n['numpy']:.0f} us"
            )
        if "malloc" not in args.skip:
            m = bench_malloc(args.rounds, args.queries, tmp)
            for name, (wall, cpu, first) in m.items():
                print(
                    f"worst-case query vs 10,000 scans, glibc {name}: {wall:.2f} ms wall, "
                    f"{cpu:.2f} ms CPU, the process's first query {first:.1f} ms CPU (medians "
                    f"over {args.rounds} processes of each one's median of "
                    f"{args.queries - 2} queries)"
                )
        if "blas" not in args.skip:
            b = bench_blas(args.rounds * 4)
            for how, (w, wo) in b.items():
                print(
                    f"one BEV's embedding, {how}: {w:.2f} ms inside blas_threads(1), "
                    f"{wo:.2f} ms without (interleaved, medians)"
                )


if __name__ == "__main__":
    main()
