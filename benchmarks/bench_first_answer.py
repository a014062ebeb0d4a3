"""Time to the first answer of a fresh `disco query` process, and where it goes.

    .venv/bin/python benchmarks/bench_first_answer.py [--runs 9] [--map data/samples/00]

1. A map of `--map` (default the 26 sample scans) is built once with `disco build-db`.
2. `disco query SCAN --db map.db --format tsv` as a fresh process, `--runs` times, each
   round running three variants one after the other (so they see the same spells of
   load on a shared machine); wall time, and the child's CPU time (user + system, all
   threads), which a busy machine inflates far less. The variants: the shipped model
   (`default`, weights from default.npz, NumPy U-Net: torch is never imported); the
   same weights from the torch checkpoint (`--model .../default.pt`: torch is imported
   to read them, as every query did before); and `python -c pass` (the interpreter's
   own start and exit). Medians and the ratio of the first two.
3. Where a fresh process spends it: each phase timed inside one fresh interpreter per
   run (NumPy, `import disco_cli.cli`, the FFT (model/fft.py), opening the map with its model,
   then reading signatures, building the index and the query itself), medians over
   `--runs`.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import REPO, disco_command, print_header

_PHASES = """
import sys, time
t0 = time.perf_counter()
import numpy
t1 = time.perf_counter()
import disco_cli.cli
t2 = time.perf_counter()
from disco_cli.model import fft
fft.backend()
t3 = time.perf_counter()
from disco_cli.maps.facade import Map
m = Map.open(sys.argv[1])
t4 = time.perf_counter()
results = list(m.query_files([sys.argv[2]], topk=10))
t5 = time.perf_counter()
assert results and results[0].error is None, results
print(t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, fft.backend(),
      any(k == "torch" or k.startswith("torch.") for k in sys.modules))
"""
_NAMES = (
    "import numpy",
    "import disco_cli.cli",
    "load the FFT",
    "open map + load model",
    "signatures + index + first query",
)


def timed(cmd: list[str], env: dict) -> tuple[float, float]:
    """(wall s, CPU s of the child: user + system, all its threads)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=9)
    ap.add_argument("--map", type=Path, default=REPO / "data" / "samples" / "00")
    ap.add_argument(
        "--scan", type=Path, default=REPO / "data" / "samples" / "01" / "velodyne" / "000005.bin"
    )
    args = ap.parse_args()
    print_header("bench_first_answer")
    from disco_cli.model import DEFAULT_WEIGHTS

    env = dict(os.environ)
    # Byte-code caches as an installed package has them (pip writes them); with this
    # set, an editable install compiles disco's 70 modules anew in every run (+0.1 s).
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    if any((REPO / "src" / "disco_cli").glob("_core*")):  # a checkout with its core built in
        env["PYTHONPATH"] = os.pathsep.join(
            [str(REPO / "src"), *filter(None, [env.get("PYTHONPATH")])]
        )
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "map.db"
        subprocess.run(
            [*disco_command(), "build-db", str(args.map), "-o", str(db)],
            check=True,
            capture_output=True,
            env=env,
        )
        query = [*disco_command(), "query", str(args.scan), "--db", str(db), "--format", "tsv"]
        variants = {
            "default (.npz, NumPy U-Net)": query,
            "default.pt (torch import)": [*query, "--model", str(DEFAULT_WEIGHTS)],
            "python -c pass": [sys.executable, "-c", "pass"],
        }
        times: dict[str, list[float]] = {k: [] for k in variants}
        cpus: dict[str, list[float]] = {k: [] for k in variants}
        phases: list[list[float]] = []
        torch_seen, backends = set(), set()
        for _ in range(args.runs):
            for name, cmd in variants.items():
                wall, cpu = timed(cmd, env)
                times[name].append(wall)
                cpus[name].append(cpu)
            out = subprocess.run(
                [sys.executable, "-c", _PHASES, str(db), str(args.scan)],
                check=True,
                capture_output=True,
                text=True,
                env=env,
            ).stdout.split()
            phases.append([float(v) for v in out[:-2]])
            backends.add(out[-2])
            torch_seen.add(out[-1])
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    cpu = {k: statistics.median(v) * 1e3 for k, v in cpus.items()}
    new, old, bare = med.values()
    cnew, cold, cbare = cpu.values()
    print(
        f"fresh `disco query` of one scan against {args.map} ({args.runs} runs, medians): "
        f"{new:.0f} ms with `default` vs {old:.0f} ms from the torch checkpoint "
        f"({old / new:.2f}x); the interpreter alone (python -c pass) {bare:.0f} ms; "
        f"the processes' CPU time (user + system, all threads) {cnew:.0f} vs {cold:.0f} ms "
        f"({cold / cnew:.2f}x), python -c pass {cbare:.0f} ms"
    )
    split = [statistics.median(p[i] for p in phases) * 1e3 for i in range(len(_NAMES))]
    print(
        "inside a fresh interpreter (medians): "
        + ", ".join(f"{n} {v:.0f}" for n, v in zip(_NAMES, split))
        + f" ms; FFT from {' / '.join(sorted(backends))}; torch imported: "
        + " / ".join(sorted(torch_seen))
    )


if __name__ == "__main__":
    main()
