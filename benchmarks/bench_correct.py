"""`disco correct` on calibrated families' worlds: ATE of the odometry, of disco correct,
and of the same pose graph given every true loop; and its time against `disco loops`.

Each world is a family's two sessions (`paper_families.FAMILIES[name].simulate_args`,
shortened to `--length-m`) joined as one sequence by `disco simulate --join`, with
odometry drifted by `--odometry-drift` (default 2 % scale, 0.04 deg of yaw a step,
0.01 m and 0.02 deg of noise a step). The true loops: each scan at least 50 scans
after an earlier one within the family's radius gets the nearest such one, with the
exact relative pose from poses.txt (what the issue's 3.6 m figure used), in the same
graph as disco correct's (`PoseGraph` with its defaults: the heading drift fitted).

Time: `disco correct SEQ --odometry ODOM -o OUT --loops-out L.csv -q` against the
baseline `disco loops SEQ -q --format tsv` (disco loops' defaults: the same detector
and confidence bar), each a fresh process, both on the default thread count; wall
seconds and CPU seconds (user + system of the child: steadier than wall time on a
shared machine). Robustness: the graph rebuilt from the loops disco correct wrote
(their pose and fit, without the confidence), with and without one false loop (the
query 25 scans before the end, "seen" as standing exactly on the earlier scan nearest
30 m from it). One line per world, then the CPU and the load.

    python benchmarks/bench_correct.py --families nclt mulran --seeds 8641 8642 8643
"""

from __future__ import annotations

import argparse
import csv
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import machine_line

from disco_cli.evaluation.paper_families import FAMILIES
from disco_cli.evaluation.trajectory import ate
from disco_cli.graph.pose_graph import PoseGraph
from disco_cli.io.poses import read_kitti_poses
from disco_cli.io.poses.geometry import quat_to_matrix

DISCO = [sys.executable, "-m", "disco_cli.cli"]


def run(*args: str) -> tuple[float, float, str]:
    """Wall and CPU seconds (user + system) of one disco command, and its output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    out = subprocess.run([*DISCO, *args], check=True, capture_output=True, text=True).stdout
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    return wall, cpu, out


def rebuilt(odo: np.ndarray, rows: list[dict], false: tuple | None = None) -> np.ndarray:
    """The graph of disco correct's written loops (with `false` added), optimized."""
    graph = PoseGraph(odo)
    for r in rows:
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix([float(r[k]) for k in ("qx", "qy", "qz", "qw")])
        T[:3, 3] = [float(r[k]) for k in ("x", "y", "z")]
        graph.add_loop(int(r["match_index"]), int(r["query_index"]), T,
                       fitness=float(r["fitness"]), rmse=float(r["rmse"]))  # fmt: skip
    if false is not None:
        graph.add_loop(*false, fitness=0.9, rmse=0.05)
    return graph.optimize().poses


def false_loop(truth: np.ndarray, exclude: int = 50) -> tuple[int, int, np.ndarray]:
    """(match, query, T): the query 25 scans before the end placed exactly on the
    earlier scan nearest 30 m away from it."""
    q = len(truth) - 26
    d = np.linalg.norm(truth[: q - exclude, :2, 3] - truth[q, :2, 3], axis=1)
    return int(np.argmin(np.abs(d - 30.0))), q, np.eye(4)


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
    args = ap.parse_args()
    print("family seed scans found graph false odometry_ate correct_ate true_loops_ate ratio "
          "false_loop_ratio loops_s correct_s time_ratio loops_cpu_s correct_cpu_s "
          "cpu_ratio")  # fmt: skip
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
                found = len(t_loops[2].splitlines()) - 1  # the header, then one row a loop
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
                clean = ate(rebuilt(odo, rows), truth)
                fooled = ate(rebuilt(odo, rows, false_loop(truth)), truth)
                print(f"{name} {seed} {len(truth)} {found} {len(rows)} {false} "
                      f"{ate(odo, truth):.2f} {got:.2f} {best:.2f} {got / best:.2f} "
                      f"{fooled / clean:.2f} {t_loops[0]:.1f} {t_correct[0]:.1f} "
                      f"{t_correct[0] / t_loops[0]:.2f} {t_loops[1]:.1f} {t_correct[1]:.1f} "
                      f"{t_correct[1] / t_loops[1]:.2f}", flush=True)  # fmt: skip
    print(f"# {machine_line()}")  # last: the load average over the runs


if __name__ == "__main__":
    main()
