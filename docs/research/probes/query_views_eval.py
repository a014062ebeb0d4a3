"""Issue 24: the query's side views as shipped, against the search before them.

    SEL=out/sel   # the selection worlds (docs/research/model-history.md, "Seeds")
    PYTHONPATH=src nice -n 5 .venv/bin/python docs/research/probes/query_views_eval.py \
        $SEL/sel5103:8.5 $SEL/sel5101:5 $SEL/sel5102:5 $SEL/s5001:5 ... $SEL/s5008:5

Each argument is WORLD:RADIUS, a `disco simulate` folder (sessions 00 and 01) and the
radius (m) within which a match is true; worlds are embedded once by the shipped model
and cached (--cache, as `query_side_views_probe.py` does). Every query goes through
`search.match_queries` with the map in memory, three ways:

- `before`: no side views of the query, the yaw search reaching 5 m (the search before
  issue 24's views, except that the snap now carries the yaw to the scan it moves to by
  the map poses, where it searched it then: that function is gone, issue 32);
- `views`: the query's side views (`DiscoModel.query_views`), the snap carrying the
  best match's yaw by the two map poses, the yaw search still reaching 5 m;
- `shipped`: as `views`, with the yaw search reaching `yaw_refine.SIDE_REACH` to the
  query's sides.

`--offsets 5` (or 4,5,6, ...) tries other views than the model's +-4 and +-6 m.

Prints Recall@1 per world (revisit worlds, radius over 5 m: by distance to the nearest
map scan, 4-5 / 5-6 / 6-7 / 7-8 m), the correct top-1s whose yaw is off by more than 10
degrees in brackets, and the mean yaw error of the correct top-1s.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]


def set_side_reach(metres: float) -> None:
    from disco_cli.model import yaw_refine

    yaw_refine._coarse_cells.__wrapped__.__defaults__ = (yaw_refine.COARSE_REACH, metres)
    yaw_refine._coarse_cells.cache_clear()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", nargs="+", help="WORLD:RADIUS")
    ap.add_argument("--cache", type=Path, default=Path("out/qsv"))
    ap.add_argument(
        "--offsets",
        default=None,
        help="the views' offsets (m, comma-separated) instead of the model's, e.g. 5 or 4,5,6",
    )
    args = ap.parse_args()
    from _common import print_header

    print_header("query_views_eval")
    import torch

    torch.set_num_threads(1)
    from query_side_views_probe import World

    from disco_cli.model import load_model, yaw_refine

    model = load_model("default")
    shipped = model.query_policy
    offsets = shipped.view_offsets
    if args.offsets:
        offsets = tuple(float(x) for x in args.offsets.split(","))
    views = replace(shipped, view_offsets=offsets)
    ways = {
        "before": (replace(shipped, view_offsets=()), 0.0),
        "views": (views, 0.0),
        "shipped": (views, yaw_refine.SIDE_REACH),
    }
    print("| world | queries | " + " | ".join(ways) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in ways) + " |")
    for spec in args.worlds:
        w = World(spec, args.cache, model)
        cells, n = [], 0
        for policy, reach in ways.values():
            set_side_reach(reach)
            errors: list[float] = []
            score = w._score

            def scored(i, best, hits, near, score=score, errors=errors, w=w):
                out = score(i, best, hits, near)
                if hits[-1]:
                    true = math.degrees(w.e["qxyyaw"][i, 2] - w.e["mpose"][best.row, 3])
                    errors.append(abs((best.yaw_deg - true + 180.0) % 360.0 - 180.0))
                return out

            w._score = scored
            r1, n, by, over10 = w.run(model, "none", None, policy=policy)
            w._score = score
            cell = f"{r1:.3f}"
            if w.radius > 5:
                cell += " (" + " / ".join(f"{b:.2f}" for b in by) + ")"
            cell += (f" [{over10}]" if over10 else "") + f", {np.mean(errors):.2f} deg"
            cells.append(cell)
        print(f"| {w.path.name} | {n} | " + " | ".join(cells) + " |", flush=True)
    set_side_reach(yaw_refine.SIDE_REACH)


if __name__ == "__main__":
    main()
