"""How often the refined yaw comes back turned around, with and without the yaw check.

    PYTHONPATH=src .venv/bin/python docs/research/probes/yaw_flip_probe.py WORLD... \\
        [--model default]

For every query of each `disco simulate` WORLD (sessions 00, 01) that has a map scan
within --radius m, the parallax-free yaw against that nearest map scan, once as it was
before the check (`check_below` = -1) and once as shipped: how many are off by
more than 10 degrees, the mean error, and how many matches the check looked at (those
with a confidence below 0.6). Issue 24's selection worlds are seeds 5101-5199
(docs/research/model-history.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", type=Path, nargs="+")
    ap.add_argument("--model", default="default")
    ap.add_argument("--radius", type=float, default=8.5)
    args = ap.parse_args()
    from _common import print_header

    print_header("yaw_flip_probe")

    import torch
    from ood_suite import embed_world

    from disco_cli.io.poses import xy_yaw
    from disco_cli.model import load_model

    torch.set_num_threads(2)
    model = load_model(args.model)
    below = model.query_policy.yaw_check_below
    for world in args.worlds:
        w = embed_world(model, world)
        mx, my, myaw = xy_yaw(w.map_poses)
        qx, qy, qyaw = xy_yaw(w.queries.poses)
        errs = {"before": [], "shipped": []}
        low = 0
        for i in range(len(qx)):
            d = np.hypot(mx - qx[i], my - qy[i])
            j = int(np.argmin(d))
            if d[j] > args.radius:
                continue
            true = np.degrees(qyaw[i] - myaw[j])
            # -1: no confidence is below it, so no second heading is searched
            for key, level in (("before", -1.0), ("shipped", below)):
                yaw, conf = model.refine_yaw_conf(
                    w.query_features[i], w.map_features[j][None], check_below=level
                )
                errs[key].append(abs((yaw[0] - true + 180.0) % 360.0 - 180.0))
                low += key == "shipped" and conf[0] < below
        parts = []
        for key, e in errs.items():
            e = np.array(e)
            parts.append(f"{key}: {int((e > 10).sum())} over 10 deg, mean {e.mean():.2f} deg")
        print(
            f"{world.name} ({args.model}, {len(errs['before'])} queries, {low} with a "
            f"confidence below {below}): " + "; ".join(parts)
        )


if __name__ == "__main__":
    main()
