"""Speed beside busy processes: the query stream and build-db, idle and beside one and
two spinning processes, with disco's default threads and with torch's own default.

    .venv/bin/python benchmarks/bench_contention.py [--map 300] [--queries 60]
        [--repeats 3] [--model default]

Issue 23 found torch's default (one intra-op thread per core) stalling beside a busy
process: a query stream 1.96x slower beside one, 3.4x beside two. This runs, in one
process and on the same scans:

- `disco query - --db map.db` streaming `--queries` scans (paths on stdin) against a
  map of `--map` scans, and `disco build-db` of those `--map` scans into a new map;
- each as a fresh `disco` process, with the defaults (`--threads` unset: 1 thread, or
  DISCO_THREADS) and, as the baseline, with torch's default intra-op threads (the
  behaviour before `--threads`: a wrapper leaves torch's setting alone);
- idle, beside one busy process and beside two (each a Python loop spinning on one
  core, started here and stopped after its condition).

Each figure is the median wall time of `--repeats` runs, settings interleaved so that
both see the same spells of outside load. Targets: beside one busy process at most
1.3x the idle time, beside two at most 1.6x. Scans are synthetic (30k points,
`_common.synthetic_scan`), written as KITTI .bin files in a temporary folder.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import REPO, model_arg, print_header, synthetic_scan

# Runs `disco` with torch's intra-op threads as torch chooses them: the pools keep one
# reader thread, as before, but nothing touches torch or the library variables.
OLD_BEHAVIOUR = """
import sys
import disco_cli.runtime.threads as t
def leave_torch_alone(n=None):
    t._current = 1
    return 1
t.set_threads = leave_torch_alone
t.ensure_threads = lambda: 1
from disco_cli.cli import main
sys.argv = ["disco", *sys.argv[1:]]
main()
"""

SPIN = "while True:\n    pass\n"
CONDITIONS = {"idle": 0, "beside 1 busy": 1, "beside 2 busy": 2}
TARGETS = {"beside 1 busy": 1.3, "beside 2 busy": 1.6}


def write_scans(folder: Path, n: int, seed: int) -> list[Path]:
    folder.mkdir(parents=True)
    paths = []
    for i in range(n):
        p = folder / f"{i:06d}.bin"
        synthetic_scan(seed + i).tofile(p)
        paths.append(p)
    return paths


def env_for() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src"), *filter(None, [env.get("PYTHONPATH")])])
    for var in ("DISCO_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(var, None)  # each setting as a new user's shell has it
    return env


def disco_argv(setting: str) -> list[str]:
    if setting == "default":
        return [sys.executable, "-m", "disco_cli.cli"]
    return [sys.executable, "-c", OLD_BEHAVIOUR]


def timed(argv: list[str], env: dict[str, str], stdin: str | None = None) -> float:
    t0 = time.perf_counter()
    res = subprocess.run(
        argv, input=stdin, env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        sys.exit(f"failed ({res.returncode}): {' '.join(argv[-6:])}\n{res.stderr[-2000:]}")
    return wall


def start_busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]


def stop_busy(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", type=int, default=300, help="scans in the map (and in build-db)")
    ap.add_argument("--queries", type=int, default=60, help="scans in the query stream")
    ap.add_argument("--repeats", type=int, default=3, help="runs per figure (median)")
    ap.add_argument("--model", default="default")
    args = ap.parse_args()
    print_header("bench_contention")
    import torch

    print(
        f"# torch {torch.__version__}: default intra-op threads here {torch.get_num_threads()}; "
        f"map {args.map} scans, {args.queries} queries, median of {args.repeats}",
        flush=True,
    )
    settings = ["default", "torch default threads"]
    with tempfile.TemporaryDirectory(prefix="disco-contention-") as tmp_name:
        tmp = Path(tmp_name)
        model, what = model_arg(args.model, tmp)
        map_dir = tmp / "map"
        write_scans(map_dir / "velodyne", args.map, 0)
        queries = write_scans(tmp / "queries", args.queries, 100_000)
        stdin = "".join(f"{p}\n" for p in queries)
        db = tmp / "map.db"
        base = disco_argv("default")
        timed([*base, "build-db", str(map_dir), "-o", str(db), "-m", model], env_for())
        print(f"# model: {what}", flush=True)

        def run(task: str, setting: str, k: int) -> float:
            argv, env = disco_argv(setting), env_for()
            if task == "query":
                return timed([*argv, "query", "-", "-d", str(db), "-k", "10"], env, stdin)
            out = tmp / f"build-{setting[:3]}-{k}.db"
            out.unlink(missing_ok=True)
            return timed([*argv, "build-db", str(map_dir), "-o", str(out), "-m", model], env)

        times: dict[tuple[str, str, str], float] = {}
        for cond, busy in CONDITIONS.items():
            procs = start_busy(busy)
            try:
                time.sleep(0.5 if busy else 0.0)  # let the spinners take their cores
                for task in ("query", "build-db"):
                    runs: dict[str, list[float]] = {s: [] for s in settings}
                    for k in range(args.repeats):
                        for s in settings:  # interleaved: both see the same outside load
                            runs[s].append(run(task, s, k))
                    for s in settings:
                        times[(task, s, cond)] = statistics.median(runs[s])
                        print(f"  {task:8s} {s:22s} {cond:14s} {times[(task, s, cond)]:6.2f} s",
                              flush=True)  # fmt: skip
            finally:
                stop_busy(procs)

    print()
    print("| task | threads | idle (s) | beside 1 busy (s, x idle) | beside 2 busy (s, x idle) |")
    print("| --- | --- | ---: | ---: | ---: |")
    verdicts = []
    for task in ("query", "build-db"):
        for s in settings:
            idle = times[(task, s, "idle")]
            cells = [f"{idle:.2f}"]
            for cond in ("beside 1 busy", "beside 2 busy"):
                t = times[(task, s, cond)]
                ratio = t / idle
                cells.append(f"{t:.2f} ({ratio:.2f}x)")
                if s == "default":
                    ok = ratio <= TARGETS[cond]
                    verdicts.append(
                        f"{task} {cond}: {ratio:.2f}x (target <= {TARGETS[cond]}x) "
                        f"{'met' if ok else 'NOT met'}"
                    )
            print(f"| {task} | {s} | " + " | ".join(cells) + " |")
        d = times[(task, "default", "beside 2 busy")]
        o = times[(task, "torch default threads", "beside 2 busy")]
        verdicts.append(f"{task} beside 2 busy: default {o / d:.2f}x faster than torch's threads")
    print()
    for v in verdicts:
        print(v)


if __name__ == "__main__":
    main()
