"""Would re-ranking by the re-centred yaw's peak help? Recall@1 on one suite world.

    .venv/bin/python docs/research/probes/rerank_recentred.py \
        out/ood/worlds/hard-terrace-16b-c45 --top 3

On a world of the out-of-distribution suite (`benchmarks/run_ood.sh` makes them under
out/ood/worlds; session 00 is the map, session 01 the queries, as the suite queries them;
--tilt adds a random tilt), the shipped search gives each query its 10 best matches.
The best --top of them are re-ordered by the peak of `yaw_refine.refine_one` on G - U
alone, and by that peak minus the learned distance; a match is true within 5 m.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]
import ood_suite as suite  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    suite.add_world_arguments(ap)
    ap.add_argument("--top", type=int, default=3, help="how many best matches to re-order")
    args = ap.parse_args()

    from _common import print_header

    from disco_cli.io.poses import xy_yaw
    from disco_cli.maps.database import Database, ModelInfo, ScanBatch
    from disco_cli.model import load_model
    from disco_cli.model.yaw_refine import refine_one
    from disco_cli.query.search import SignatureIndex, match_queries

    print_header("rerank_recentred")
    model = load_model("default")
    max_range = model.bev_config.max_range
    world = suite.embed_world(model, args.world, args.tilt)
    mf, qf = world.map_features, world.query_features
    mx, my, myaw = xy_yaw(world.map_poses)
    qx, qy, _ = xy_yaw(world.queries.poses)
    pose4 = np.c_[mx, my, world.map_poses[:, 2, 3], myaw]
    with tempfile.TemporaryDirectory() as tmp:
        paths = [str(p) for p in world.map_paths]
        batch = ScanBatch(paths, world.map_signatures, mf, pose4)
        with Database.create(Path(tmp) / "map.db", ModelInfo.of(model), batch) as db:
            ids, sigs = db.signatures()
            no_refine = replace(model.query_policy, refine_yaw=0)
            found = match_queries(
                SignatureIndex(sigs), ids, db, model, world.query_signatures, qf, 10, no_refine
            )
    hits = {"shipped order": 0, "peak": 0, "peak - distance": 0}
    n = 0
    for i, matches in enumerate(found):
        d = np.hypot(mx - qx[i], my - qy[i])
        if d.min() > suite.RADIUS or not matches:
            continue
        n += 1
        top = matches[: args.top]
        rows = [m.row for m in top]
        dist = np.array([m.distance for m in top])
        peak = np.array(
            [
                refine_one(model.refine_image(qf[i]), model.refine_image(mf[r]), max_range)[2]
                for r in rows
            ]
        )
        hits["shipped order"] += d[rows[0]] <= suite.RADIUS
        hits["peak"] += d[rows[int(np.argmax(peak))]] <= suite.RADIUS
        hits["peak - distance"] += d[rows[int(np.argmax(peak - dist))]] <= suite.RADIUS
    print(f"{args.world.name}: {n} queries, re-ordering the best {args.top}")
    for name, h in hits.items():
        print(f"  Recall@1 by {name:15s} {h / n:.3f}")


if __name__ == "__main__":
    main()
