"""Issue 41 probe: where the wider re-ranking pass fires, and where it gains.

    .venv/bin/python benchmarks/paper_table.py --seeds selection --families nclt mulran \
        oxford --models default --no-loops --policy rerank_wider=0
    .venv/bin/python docs/research/probes/wider_pass_probe.py [--worlds out/paper/worlds]

The first command caches every selection world's query rows without the wider pass
(`out/paper/rows/*--query--default--*.jsonl`, policy `rerank_wider` 0). This probe then
queries the same worlds with the shipped policy (`paper_families.evaluate`), recording
for each query whether the wider pass fired (a second re-ranking call) and the first
pass's best re-rank distance; a query gains where its top 1 is right with the pass and
wrong without it (a loss, the other way round). Prints per family: how often the pass
fires, how often where the query has no true match at all, its gains and losses, and
the first pass's best distance where it fired (min / median / max) against where it
gained.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from disco_cli.evaluation import paper_families
from disco_cli.query import search

SEEDS = paper_families.SEEDS["selection"]
FAMILIES = ("nclt", "mulran", "oxford")


def rows_without_wider(rows_dir: Path, world: str) -> dict[int, dict]:
    """The newest cached rows of `world` queried with `rerank_wider` 0, by query."""
    newest: tuple[float, Path] | None = None
    for path in rows_dir.glob(f"{world}--query--default--*.jsonl"):
        with path.open() as fh:
            head = json.loads(fh.readline())
        if head["policy"]["rerank_wider"] == 0 and (
            newest is None or path.stat().st_mtime > newest[0]
        ):
            newest = (path.stat().st_mtime, path)
    if newest is None:
        sys.exit(f"{world}: no rows without the wider pass under {rows_dir}; run paper_table first")
    lines = newest[1].read_text().splitlines()[1:]
    return {row["query"]: row for row in map(json.loads, lines)}


def record_passes() -> list[dict]:
    """Wraps the re-ranking so that each query's passes are recorded, in query order."""
    passes: list[dict] = []
    reranked, call = search._reranked, search._Reranker.__call__

    def reranked_spy(*args, **kwargs):
        passes.append({"best": []})
        return reranked(*args, **kwargs)

    def call_spy(self, features):
        own, best = call(self, features)
        passes[-1]["best"].append(float(best.min()) if len(best) else np.inf)
        return own, best

    search._reranked = reranked_spy
    search._Reranker.__call__ = call_spy
    return passes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=Path, default=Path("out/paper/worlds"))
    ap.add_argument("--rows", type=Path, default=Path("out/paper/rows"))
    args = ap.parse_args()
    passes = record_passes()
    for family in FAMILIES:
        fired = gains = losses = fired_no_match = queries = 0
        best_fired, best_gained = [], []
        for seed in SEEDS:
            world = f"{family}-{seed}"
            before = rows_without_wider(args.rows, world)
            passes.clear()
            rows = paper_families.evaluate(
                paper_families.FAMILIES[family], args.worlds / world, "default"
            )
            assert len(rows) == len(passes) == len(before), world
            for row, p in zip(rows, passes):
                was = before[row["query"]]
                queries += 1
                gained, lost = row["r1"] and not was["r1"], was["r1"] and not row["r1"]
                gains, losses = gains + gained, losses + lost
                if len(p["best"]) > 1:
                    fired += 1
                    fired_no_match += not row["has"]
                    best_fired.append(p["best"][0])
                    if gained:
                        best_gained.append(p["best"][0])
        print(
            f"{family}: {queries} queries; the wider pass fired on {fired} "
            f"({fired / queries:.0%}), {fired_no_match} of them without a true match in "
            f"the map; {gains} top-1s gained, {losses} lost"
        )
        if best_fired:
            q = np.percentile(best_fired, [0, 50, 100]).round(3)
            print(f"  first pass's best distance where it fired: {q[0]} / {q[1]} / {q[2]}")
        if best_gained:
            print(f"  where it gained: {min(best_gained):.3f} to {max(best_gained):.3f}")


if __name__ == "__main__":
    main()
