"""`disco correct` on calibrated families' worlds: ATE of the odometry, of disco correct,
and of the same pose graph given every true loop; and its time against `disco loops`.

Each world is a family's two sessions (`paper_families.FAMILIES[name].simulate_args`,
shortened to `--length-m`) joined as one sequence by `disco simulate --join`, with
odometry drifted by `--odometry-drift` (default 2 % scale, 0.04 deg of yaw a step,
0.01 m and 0.02 deg of noise a step). The true loops: each scan at least 50 scans
after an earlier one within the family's radius gets the nearest such one, with the
exact relative pose from poses.txt (what the issue's 3.6 m figure used). One line per
world, then the CPU.

    python benchmarks/bench_correct.py --families nclt mulran --seeds 8641 8642 8643
"""

from __future__ import annotations

import argparse
import csv
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import cpu_model

from disco_cli.evaluation.paper_families import FAMILIES
from disco_cli.evaluation.trajectory import ate
from disco_cli.graph.pose_graph import PoseGraph
from disco_cli.io.poses import read_kitti_poses

DISCO = [sys.executable, "-m", "disco_cli.cli"]


def run(*args: str) -> float:
    start = time.perf_counter()
    subprocess.run([*DISCO, *args], check=True, capture_output=True, text=True)
    return time.perf_counter() - start


def true_loops(truth: np.ndarray, radius: float, exclude: int = 50) -> list:
    xy = truth[:, :2, 3]
    loops = []
    for i in range(exclude, len(truth)):
        d = np.linalg.norm(xy[: i - exclude + 1] - xy[i], axis=1)
        j = int(np.argmin(d))
        if d[j] <= radius:
            loops.append((j, i, np.linalg.inv(truth[j]) @ truth[i]))
    return loops


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", nargs="+", default=["nclt", "mulran"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[8641])
    ap.add_argument("--scans", type=int, default=250, help="scans per session")
    ap.add_argument("--odometry-drift", default="0.02,0.04,0.01,0.02")
    ap.add_argument("--false-loop", action="store_true", help="also inject one false loop")
    args = ap.parse_args()
    print("family seed scans loops false odometry_ate correct_ate true_loops_ate ratio "
          "loops_s correct_s")  # fmt: skip
    for name in args.families:
        fam = FAMILIES[name]
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / "w"
                sim = fam.simulate_args(seed)
                i = sim.index("--length-m")
                sim[i + 1] = f"{args.scans * fam.step_m:g}"
                run("simulate", str(out), *sim, "--odometry-drift", args.odometry_drift,
                    "--join", "-q")  # fmt: skip
                seq = out / "joined"
                truth = read_kitti_poses(seq / "poses.txt")
                odo = read_kitti_poses(seq / "odometry.txt")
                t_loops = run("loops", str(seq), "-q", "--format", "tsv")
                corrected = Path(tmp) / "c.txt"
                loops_csv = Path(tmp) / "loops.csv"
                t_correct = run("correct", str(seq), "--odometry", str(seq / "odometry.txt"),
                                "-o", str(corrected), "--loops-out", str(loops_csv),
                                "-q")  # fmt: skip
                with open(loops_csv) as fh:
                    rows = list(csv.DictReader(fh))
                xy = truth[:, :2, 3]
                false = sum(
                    np.linalg.norm(xy[int(r["query_index"])] - xy[int(r["match_index"])])
                    > fam.radius + 5.0
                    for r in rows
                )
                graph = PoseGraph(odo)
                for j, k, T in true_loops(truth, fam.radius):
                    graph.add_loop(j, k, T, fitness=1.0, rmse=0.05)
                best = ate(graph.optimize().poses, truth)
                got = ate(read_kitti_poses(corrected), truth)
                print(f"{name} {seed} {len(truth)} {len(rows)} {false} {ate(odo, truth):.2f} "
                      f"{got:.2f} {best:.2f} {got / best:.2f} {t_loops:.1f} {t_correct:.1f}",
                      flush=True)  # fmt: skip
    print(f"# {cpu_model()}, {platform.python_version()}")


if __name__ == "__main__":
    main()
