"""The yaw error of `disco query --pose` (ICP-refined) against a world's ground truth.

    disco build-db WORLD/00 -o map.db
    disco query WORLD/01 --db map.db --topk 1 --pose --format jsonl > q.jsonl
    .venv/bin/python docs/research/probes/pose_yaw_error.py WORLD q.jsonl [--radius 5]

Over the queries whose top match lies within --radius of them (the suite's protocol),
prints the mean, median and largest error of the refined `yaw_deg` (the yaw of
T_match<-query) and how many are off by more than 5 and 90 degrees: over all of them,
and over those whose pose was accepted (what `--verify` keeps). The out-of-distribution
suite scores the phase-correlation yaw that `disco eval` reports; this is what a user who
asks for `--pose` gets on the same worlds (docs/research/model-history.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def yaw_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def main() -> int:
    from disco_cli.io.poses import read_kitti_poses

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("world", type=Path, help="a simulated world: sessions 00 (map) and 01")
    ap.add_argument("jsonl", type=Path, help="`disco query 01 --pose --format jsonl` output")
    ap.add_argument("--radius", type=float, default=5.0)
    args = ap.parse_args()

    def poses(session: str) -> np.ndarray:
        calib = args.world / session / "calib.txt"
        return read_kitti_poses(
            args.world / session / "poses.txt", calib if calib.is_file() else None
        )

    map_poses, query_poses = poses("00"), poses("01")
    errors, accepted = [], []
    for line in args.jsonl.read_text().splitlines():
        row = json.loads(line)
        if row.get("rank", 1) != 1 or "yaw_deg" not in row:
            continue
        Tq = query_poses[int(Path(row["query"]).stem)]
        Tm = map_poses[int(Path(row["match"]).stem)]
        if np.linalg.norm(Tq[:3, 3] - Tm[:3, 3]) > args.radius:
            continue  # a wrong place: no yaw to score
        truth = yaw_deg(np.linalg.inv(Tm) @ Tq)
        errors.append(abs((row["yaw_deg"] - truth + 180.0) % 360.0 - 180.0))
        accepted.append(bool(row.get("accepted")))
    e, ok = np.array(errors), np.array(accepted, bool)
    if not len(e):
        print("no correct top-1 match")
        return 1
    for label, sel in (("correct top-1 matches", e), ("of them accepted", e[ok])):
        if len(sel):
            print(
                f"{len(sel)} {label}: refined yaw error mean {sel.mean():.2f}, "
                f"median {np.median(sel):.2f}, max {sel.max():.1f} deg; "
                f"{(sel > 5).sum()} over 5 deg, {(sel > 90).sum()} over 90 deg"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
