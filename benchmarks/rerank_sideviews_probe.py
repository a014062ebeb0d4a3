"""Issue 24 probe: the network with and without re-ranking, with and without side views.

    PYTHONPATH=src .venv/bin/python benchmarks/rerank_sideviews_probe.py WORLD \
        [--radius 8.5] [--side-views 0 5]

WORLD is a `disco simulate` folder (sessions 00 and 01), evaluated as the suite does
(`ood_suite.evaluate`: the map stored with the library's Database, every query through
`search.match_queries`), once with the model's re-ranking (and the snap that needs it)
and once with `rerank_candidates = 0` (`disco query --rerank 0`), for each side-view
distance (`disco build-db --side-views M`; 0: none). Prints Recall@1, the mean yaw error
and the correct matches off by more than 10 degrees.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("--model", default="default")
    ap.add_argument("--radius", type=float, default=8.5)
    ap.add_argument("--side-views", type=float, nargs="+", default=[0.0, 5.0])
    args = ap.parse_args()
    from _common import print_header

    print_header("rerank_sideviews_probe")
    import ood_suite as suite
    import torch

    torch.set_num_threads(2)
    seed = int(json.loads((args.world / "world.json").read_text())["seed"])
    mp, mpose = suite.load_session(args.world / "00")
    qp, qpose = suite.load_session(args.world / "01")
    queries = suite.Queries(qp, qpose, 0.0, seed=seed)
    for sv in args.side_views:
        for rerank in (True, False):
            model = suite.load_suite_model(args.model)
            policy = model.query_policy
            if not rerank:
                policy = replace(policy, rerank_candidates=0)
            rows = suite.evaluate(model, mp, mpose, queries, 2, sv, 1, args.radius, policy)
            s = suite.summarize(rows)
            print(
                f"{args.world.name} {args.model} side views {sv:g} m, "
                f"{'re-ranked' if rerank else '--rerank 0'}: Recall@1 {s['r1']:.3f} "
                f"({s['n']} queries), yaw error mean {s['yaw_mean']:.2f} deg, "
                f"{s['yaw_over10']} of {s['hits']} over 10 deg",
                flush=True,
            )


if __name__ == "__main__":
    main()
