"""Issue 24 probe: orders of the re-ranked candidates, tried offline on cached embeddings.

    PYTHONPATH=src .venv/bin/python docs/research/probes/revisit_rerank_probe.py \
        out/sel/sel5103:8.5:5 out/sel/s5008:5:0 ... [--cache out/rrprobe]

Each argument is WORLD:RADIUS:SIDE_VIEWS: a `disco simulate` folder (sessions 00 and 01,
as the suite reads them), the radius (m) within which a match is true, and the side
views' offset (m, 0: none). Each world is embedded once by the shipped model (map
scans, their side views at 2.5, 4, 5 and 6 m, the queries) and cached under --cache.
Every query then goes the way `search.match_queries` takes it: its 10 nearest scans by
signature (a scan at its nearest signature, side views included, as
`side_views.ViewIndex` answers), re-ranked by the model, 40 where none of the 10
re-ranks better than 0.7, ordered by each rule below, snapped to the map scan nearest
the query's estimated position (`search.snap_to_nearest_conf`, margin on the re-rank
distance). Prints Recall@1 per rule (revisits: by distance to the nearest map scan,
4-5 / 5-6 / 6-7 / 7-8 m). Rules: the re-rank distance r alone (shipped before), r +
a d (linear), r + a ln d, and r - a / d (shipped), d the signature distance.
"""

from __future__ import annotations

import argparse
import json
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

OFFSETS = (2.5, 4.0, 5.0, 6.0)


def embedded(world: Path, cache: Path, model) -> dict[str, np.ndarray]:
    import ood_suite as suite

    from disco_cli.embedding.load import seen_from
    from disco_cli.io.poses import xy_yaw
    from disco_cli.io.readers import read_scan

    f = cache / f"{world.name}.npz"
    if f.is_file():
        return dict(np.load(f))
    seed = int(json.loads((world / "world.json").read_text())["seed"])
    mp, mpose = suite.load_session(world / "00")
    qp, qpose = suite.load_session(world / "01")
    queries = suite.Queries(qp, qpose, 0.0, seed=seed)
    ms, mf = suite.embed(model, lambda i: read_scan(mp[i]), len(mp), 2)
    offs = [s * o for o in OFFSETS for s in (1, -1)]
    v = len(offs)
    vs, _ = suite.embed(
        model, lambda j: seen_from(read_scan(mp[j // v]), offs[j % v]), v * len(mp), 2
    )
    qs, qf = suite.embed(model, queries.points, len(qp), 2)
    mx, my, myaw = xy_yaw(mpose)
    qx, qy, qyaw = xy_yaw(queries.poses)
    out = {
        "ms": ms,
        "mf": mf,
        "vs": vs.reshape(len(mp), v, -1),
        "offs": np.array(offs),
        "qs": qs,
        "qf": qf,
        "mpose": np.c_[mx, my, mpose[:, 2, 3], myaw],
        "qxyyaw": np.c_[qx, qy, qyaw],
    }
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(f, **out)
    return out


RULES: dict[str, object] = {"r": lambda r, d, a: r}
RULES.update({f"r+{a:g}d": (lambda a: lambda r, d, _: r + a * d)(a) for a in (1, 2, 3)})  # noqa: B023
RULES.update({f"r+{a:g}ln d": (lambda a: lambda r, d, _: r + a * np.log(d))(a) for a in (0.5,)})  # noqa: B023
RULES.update({f"r-{a:g}/d": (lambda a: lambda r, d, _: r - a / d)(a) for a in (0.1, 0.2, 0.3, 0.4)})  # noqa: B023


class Evaluated:
    """One world's candidates per query: signature distances, re-rank distances of the 40
    nearest, and the query's position estimated from a map scan (computed when asked)."""

    def __init__(self, e: dict[str, np.ndarray], model, radius: float, side_views: float):
        self.e, self.model, self.radius = e, model, radius
        mp, q = e["mpose"], e["qxyyaw"]
        self.mp = mp
        self.true_d = np.hypot(mp[None, :, 0] - q[:, None, 0], mp[None, :, 1] - q[:, None, 1])
        own = np.linalg.norm(e["ms"][None] - e["qs"][:, None], axis=2)
        sel = np.flatnonzero(np.isclose(np.abs(e["offs"]), side_views)) if side_views else []
        best = own
        if len(sel):
            views = np.linalg.norm(e["vs"][:, sel][None] - e["qs"][:, None, None], axis=3)
            best = np.minimum(own, views.min(axis=2))
        self.top = np.argsort(best, axis=1, kind="stable")[:, :40]
        self.sig = np.take_along_axis(best, self.top, axis=1)
        self.rr = np.stack(
            [model.rerank_distances(e["qf"][i], e["mf"][t]) for i, t in enumerate(self.top)]
        ).astype(np.float64)
        self._estimates: dict[tuple[int, int], np.ndarray] = {}

    def estimate(self, i: int, j: int) -> np.ndarray:
        if (i, j) not in self._estimates:
            from disco_cli.query.search import query_on_map_conf

            _, xy, _ = query_on_map_conf(self.model, self.e["qf"][i], self.e["mf"][j], self.mp[j])
            self._estimates[(i, j)] = xy
        return self._estimates[(i, j)]

    def recall(self, rule) -> tuple[float, int, list[float]]:
        from disco_cli.query.query_policy import QueryPolicy

        shipped = QueryPolicy()
        RERANK_WIDER_ABOVE = shipped.rerank_wider_above  # noqa: N806
        SNAP_MARGIN, SNAP_RADIUS = shipped.snap_margin, shipped.snap_radius  # noqa: N806

        hits, near = [], []
        for i in np.flatnonzero(self.true_d.min(axis=1) <= self.radius):
            top, rr, sig = self.top[i], self.rr[i], self.sig[i]
            n = 40 if rr[:10].min() > RERANK_WIDER_ABOVE else 10
            order = np.lexsort((top[:n], rule(rr[:n], sig[:n], None)))
            b = order[0]
            xy = self.mp[top[order], :2]
            near_b = np.hypot(*(xy - self.mp[top[b], :2]).T) <= SNAP_RADIUS
            alike = rr[order] <= rr[b] + SNAP_MARGIN
            cands = order[near_b & alike]
            est = self.estimate(i, top[b])
            first = cands[np.argmin(np.hypot(*(self.mp[top[cands], :2] - est).T))]
            hits.append(self.true_d[i, top[first]] <= self.radius)
            near.append(self.true_d[i].min())
        hits, near = np.array(hits), np.array(near)
        bands = [(near >= a) & (near < a + 1) for a in (4, 5, 6, 7)]
        by = [float(hits[b].mean()) if b.any() else float("nan") for b in bands]
        return float(hits.mean()), len(hits), by


def time_rule(e: dict[str, np.ndarray], model, reps: int = 5) -> None:
    """Median time per query of `search.match_queries` (one query at a time, the world's
    map in memory) with the shipped weight and with 0, interleaved in this process."""
    import time

    from disco_cli.maps.database import MatchRows
    from disco_cli.query.search import SignatureIndex, match_queries

    paths = [f"scan{i}" for i in range(len(e["ms"]))]

    class Memory:
        def rows(self, ids: np.ndarray) -> MatchRows:
            ids = np.asarray(ids, np.int64)
            return MatchRows(ids, [paths[i] for i in ids], e["mpose"][ids], e["mf"][ids])

    index, ids, db = SignatureIndex(e["ms"]), np.arange(len(e["ms"])), Memory()
    weight = model.query_policy.signature_weight
    times: dict[float, list[float]] = {weight: [], 0.0: []}
    for _ in range(reps):
        for i in range(len(e["qs"])):
            for w in (weight, 0.0):
                p = replace(model.query_policy, signature_weight=w)
                t = time.perf_counter()
                match_queries(index, ids, db, model, e["qs"][i : i + 1], e["qf"][i : i + 1], 10, p)
                times[w].append(time.perf_counter() - t)
    a, b = (1e3 * float(np.median(times[w])) for w in (weight, 0.0))
    print(
        f"match_queries per query: {a:.2f} ms with weight {weight:g}, {b:.2f} ms with 0 "
        f"(median of {len(times[0.0])}; ratio {a / b:.3f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", nargs="+", help="WORLD:RADIUS:SIDE_VIEWS")
    ap.add_argument("--cache", type=Path, default=Path("out/rrprobe"))
    ap.add_argument("--time", action="store_true", help="time match_queries on the first world")
    args = ap.parse_args()
    from _common import print_header

    print_header("revisit_rerank_probe")
    import torch

    torch.set_num_threads(2)
    from disco_cli.model import load_model

    model = load_model("default")
    if args.time:
        time_rule(embedded(Path(args.worlds[0].rsplit(":", 2)[0]), args.cache, model), model)
        return
    print("| world | side views | queries | " + " | ".join(RULES) + " |")
    print("| --- | ---: | ---: | " + " | ".join("---:" for _ in RULES) + " |")
    for spec in args.worlds:
        world, radius, sv = spec.rsplit(":", 2)
        ev = Evaluated(embedded(Path(world), args.cache, model), model, float(radius), float(sv))
        cells = []
        for rule in RULES.values():
            r1, n, by = ev.recall(rule)
            cells.append(
                f"{r1:.3f}"
                + (" (" + " / ".join(f"{b:.2f}" for b in by) + ")" if float(radius) > 5 else "")
            )
        print(
            f"| {Path(world).name} | {float(sv):g} | {n} | " + " | ".join(cells) + " |", flush=True
        )


if __name__ == "__main__":
    main()
