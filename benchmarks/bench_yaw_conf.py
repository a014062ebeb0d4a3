"""What the yaw check and the yaw confidence add to a query (issue 24).

    PYTHONPATH=src .venv/bin/python benchmarks/bench_yaw_conf.py WORLD [--model default]

WORLD is a `disco simulate` folder (sessions 00 and 01). Each query of session 01 is
paired with its nearest map scan (the true match) and the 9 map scans after it (the other
rows of a top-10 answer). Per query, medians over the queries of the CPU time of this
process (on a shared machine its wall time mostly measures the other processes), all in
this process:

- the parallax-free yaw of the best match without the check (`check_below` = -1: what
  `refine_yaw` did before) against with it (the default: the second heading searched
  only where the confidence is below 0.6), and with it forced on every match (the worst
  case: every match ambiguous); each starts without the query's kept views, as a new
  query does;
- the plain phase-correlation yaw of the 9 other rows against the same with their
  confidence (`yaw_conf`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("--model", default="default")
    ap.add_argument("--queries", type=int, default=60)
    args = ap.parse_args()
    from _common import print_header

    print_header("bench_yaw_conf")

    import torch
    from ood_suite import embed_world

    from disco_cli.io.poses import xy_yaw
    from disco_cli.model import load_model, yaw_refine

    torch.set_num_threads(2)
    model = load_model(args.model)
    w = embed_world(model, args.world)
    mx, my, _ = xy_yaw(w.map_poses)
    qx, qy, _ = xy_yaw(w.queries.poses)
    pairs = []
    for i in range(len(qx)):
        d = np.hypot(mx - qx[i], my - qy[i])
        j = int(np.argmin(d))
        if d[j] <= 5.0 and j + 10 <= len(mx):
            pairs.append((i, j))
    pairs = pairs[: args.queries]
    below = model.query_policy.yaw_check_below
    times = {"plain": [], "checked": [], "forced": [], "coarse": [], "coarse_conf": []}
    checked = 0
    for i, j in pairs:
        q, m = w.query_features[i], w.map_features[j : j + 1]
        rest = w.map_features[j + 1 : j + 10]
        for key, level in (("plain", -1.0), ("checked", below), ("forced", 1.01)):
            yaw_refine.forget_kept_views()  # each as a new query would pay it
            t = time.process_time()
            _, conf = model.refine_yaw_conf(q, m, check_below=level)
            times[key].append(time.process_time() - t)
            if key == "checked":
                checked += int(conf[0] < below or level > 1)
        t = time.process_time()
        model.yaw(q, rest)
        times["coarse"].append(time.process_time() - t)
        t = time.process_time()
        model.yaw_conf(q, rest)
        times["coarse_conf"].append(time.process_time() - t)
    ms = {k: 1000 * float(np.median(v)) for k, v in times.items()}
    print(f"{args.world.name}, model {args.model}, {len(pairs)} queries with their true match")
    print(
        f"  best match's parallax-free yaw: {ms['plain']:.2f} ms without the check, "
        f"{ms['checked']:.2f} ms with it ({ms['checked'] / ms['plain']:.2f}x; {checked} of "
        f"{len(pairs)} with a confidence below {below}), {ms['forced']:.2f} ms with every "
        f"match checked ({ms['forced'] / ms['plain']:.2f}x)"
    )
    print(
        f"  9 other rows' yaw: {ms['coarse']:.2f} ms, with their confidence "
        f"{ms['coarse_conf']:.2f} ms (+{ms['coarse_conf'] - ms['coarse']:.2f} ms)"
    )


if __name__ == "__main__":
    main()
