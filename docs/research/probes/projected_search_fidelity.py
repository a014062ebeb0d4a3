"""How often the views' approximate search (`signature_index.ProjectedSignatures`) returns
what the exact search does, by projected dimensions and widening.

    PYTHONPATH=src .venv/bin/python docs/research/probes/projected_search_fidelity.py \
        out/sel/sel5103:8.5 out/sel/sel5101:5 ... out/sel/s5008:5 --cache out/qsv

The map is every world's map and query signatures together (5,700 rows for the eleven
selection worlds); the queries are the side views (`DiscoModel.query_views`) of every
fifth query of each world. Prints, per setting, the share of views whose nearest row is
the exact one and the mean overlap of the 10 nearest with the exact 10.
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
    ap.add_argument("worlds", nargs="+", help="WORLD:RADIUS")
    ap.add_argument("--cache", type=Path, default=Path("out/qsv"))
    args = ap.parse_args()
    from _common import print_header

    print_header("projected_search_fidelity")
    from query_side_views_probe import World

    from disco_cli.maps import signature_index
    from disco_cli.maps.signature_index import SignatureIndex
    from disco_cli.model import load_model

    model = load_model("default")
    rows, views = [], []
    for spec in args.worlds:
        w = World(spec, args.cache, model)
        rows += [w.e["ms"], w.e["qs"]]
        offsets = model.query_policy.view_offsets
        views += [model.query_views(f, offsets)[0] for f in w.e["qf"][::5]]
    sigs, q = np.concatenate(rows), np.concatenate(views)
    exact, _ = SignatureIndex(sigs, int8_min_rows=1 << 62).search(q, 10)
    print(f"map {len(sigs)} rows, {len(q)} view queries")
    print("| dims | widen | nearest the exact one | overlap of the 10 nearest |")
    print("| ---: | ---: | ---: | ---: |")
    for dims in (48, 64, 96, 128):
        proj = signature_index.ProjectedSignatures(sigs, dims)
        for widen in (2, 4, 8):
            signature_index.PROJECTED_WIDEN = widen
            got, _ = proj.search(q, 10)
            top1 = float(np.mean(got[:, 0] == exact[:, 0]))
            overlap = np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, exact)])
            print(f"| {dims} | {widen} | {top1:.3f} | {overlap:.3f} |", flush=True)


if __name__ == "__main__":
    main()
