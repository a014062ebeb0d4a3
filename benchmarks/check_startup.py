"""Start-up guard (issue 41): the first answer of a fresh `disco query`, as a ratio to
`python -c "import numpy"` measured in the same run; exits 1 above a threshold.

    .venv/bin/python benchmarks/check_startup.py [--runs 7] [--max-ratio 4.0]

`make test` runs it, so CI fails when a dependency release (typer 0.29 read every
option through Pydantic) or a change of ours makes start-up several times slower. A
ratio, not seconds, so that a slower CPU fails no more than a faster one: both
processes start the interpreter and import NumPy, which scale with the machine alike.
Each is run `--runs` times, alternately (they see the same spells of load on a shared
machine), and the fastest of each is kept: load only ever adds time, so the minimum is
the least noisy estimate of the cost itself.

The threshold leaves about twice today's ratio for noise: 1.8-2.1 on the 2-core AMD
EPYC with typer 0.29.2 (docs/benchmarks.md, "Start-up and typer's releases"), where
a first answer three times as slow (what typer 0.29 did in the issue's measurements)
reads 5-6. `DISCO_STARTUP_SLOWDOWN=3` shows the guard failing: each `disco query` child
then spins at exit for twice the time it took, the process taking three times as long.

Also printed, not checked: how many modules the query loads and whether Pydantic is
among them (a release that brings a heavy import in shows there first).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SCAN = REPO / "data" / "samples" / "01" / "velodyne" / "000005.bin"
MAP = REPO / "data" / "samples" / "00"

# The `disco query` child: disco's own entry point, in this interpreter. At exit: the
# module count and whether Pydantic loaded; with DISCO_STARTUP_SLOWDOWN=F, a busy spin of
# (F - 1) x the time since its first line, as if start-up and first answer took F times.
_CHILD = """
import atexit, os, sys, time
def _at_exit():
    if os.environ.get("DISCO_STARTUP_REPORT"):
        with open(os.environ["DISCO_STARTUP_REPORT"], "w") as fh:
            fh.write(f"{len(sys.modules)} {'pydantic' in sys.modules}")
    factor = float(os.environ.get("DISCO_STARTUP_SLOWDOWN") or 1)
    end = time.perf_counter() + (factor - 1) * (time.perf_counter() - _t0)
    while time.perf_counter() < end:
        pass
atexit.register(_at_exit)
from disco_cli.cli import main
sys.argv[0] = "disco"
main()
"""


def run(cmd: list[str], env: dict) -> tuple[float, float]:
    """(wall s, CPU s of the child: user + system, all its threads)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--max-ratio", type=float, default=4.0)
    args = ap.parse_args()

    env = dict(os.environ)
    # Byte-code caches as an installed package has them (pip writes them; an editable
    # install writes them at the warm-up run below), whatever the shell says.
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "map.db"
        child = [sys.executable, "-c", f"import time; _t0 = time.perf_counter()\n{_CHILD}"]
        subprocess.run(
            [*child, "build-db", str(MAP), "-o", str(db), "-q"],
            check=True,
            stdout=subprocess.DEVNULL,
            env={**env, "DISCO_STARTUP_SLOWDOWN": ""},
        )
        query = [*child, "query", str(SCAN), "--db", str(db), "--format", "tsv"]
        numpy = [sys.executable, "-c", "import numpy"]
        report = Path(tmp) / "report"
        run(query, {**env, "DISCO_STARTUP_REPORT": str(report)})  # warm-up, and the count
        run(numpy, env)
        times: dict[str, list[tuple[float, float]]] = {"query": [], "numpy": []}
        for _ in range(args.runs):
            times["query"].append(run(query, env))
            times["numpy"].append(run(numpy, env))
        modules, pydantic = report.read_text().split() if report.exists() else ("?", "?")
    wall = {k: min(w for w, _ in v) for k, v in times.items()}
    cpu = {k: min(c for _, c in v) for k, v in times.items()}
    ratio = cpu["query"] / cpu["numpy"]
    slowdown = env.get("DISCO_STARTUP_SLOWDOWN")
    verdict = "ok" if ratio <= args.max_ratio else "TOO SLOW"
    print(
        f"check_startup: a fresh `disco query` to its answer {cpu['query'] * 1e3:.0f} ms of CPU, "
        f"`import numpy` {cpu['numpy'] * 1e3:.0f} ms (least of {args.runs} runs each; wall "
        f"{wall['query'] * 1e3:.0f} and {wall['numpy'] * 1e3:.0f} ms, load "
        f"{os.getloadavg()[0]:.1f}): ratio {ratio:.2f}, limit {args.max_ratio:.2f}: {verdict}; "
        f"{modules} modules loaded, Pydantic among them: {pydantic}"
        + (f"; DISCO_STARTUP_SLOWDOWN={slowdown}" if slowdown else "")
    )
    if ratio > args.max_ratio:
        print(
            "check_startup: start-up is several times slower than it was; see "
            "docs/benchmarks.md, 'Start-up and typer's releases' (python -X importtime "
            "and cProfile of `disco query` show where)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
