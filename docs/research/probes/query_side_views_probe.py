"""Issue 24 probe: query-side views, the query seen again from beside itself.

    SEL=out/sel   # the selection worlds (model-history.md, "Seeds")
    PYTHONPATH=src nice -n 15 .venv/bin/python docs/research/probes/query_side_views_probe.py \
        $SEL/sel5103:8.5 $SEL/sel5101:5 $SEL/sel5102:5 \
        $(for i in 1 2 3 4 5 6 7 8; do echo $SEL/s500$i:5; done) --cache out/qsv --bev
    PYTHONPATH=src nice -n 15 .venv/bin/python docs/research/probes/query_side_views_probe.py \
        $SEL/sel5103:8.5 --cache out/qsv --time      # also $SEL/s5001:5, $SEL/sel5102:5

Each argument is WORLD:RADIUS, a `disco simulate` folder (sessions 00 and 01, as the
suite reads them) and the radius (m) within which a match is true. Worlds are embedded
once by the shipped model as `revisit_rerank_probe.embedded` does (its cache files can
be copied into --cache). Every query goes through `search.match_queries` as shipped
(re-ranking, wider pass, the signature in the order, snap, refined yaw), the map held in
memory; only the signature search changes:

- `today`: the query's signature against the map scans' own;
- `map sv5`: map side views at +-5 m (`build-db --side-views 5`, `side_views.ViewIndex`);
- `G yN`: the query's signature and those of its feature image G re-centred
  (`yaw_refine.recentre`) at +-N m along its own y axis (`xyN`: along x too; `y4-6`:
  +-4, 5, 6 m), each map scan at its nearest distance over the query's views;
- `G+U y5`: as `G y5`, and the re-rank distance of each candidate is the smallest over
  the query's U (the image re-ranking compares), its own and re-centred the same way;
  `U y5`: that re-ranking alone, with today's signature search;
- `BEV y5` (--bev): views made as map side views are, from the query's points re-centred
  and embedded again (one U-Net pass per view): what query-side views can do at best;
  `BEV+U y5`: also re-ranked with those views' own U, as `G+U`;
- rules against regressions (`VARIANTS`): `+0.03` on a view's re-rank distance, `x1.05`
  on a view's signature distance, `if r>T` (views only where today's answer re-ranks
  worse than T), `own` (the wider pass keeps today's 40 nearest, `QueryViewIndex`).

Prints Recall@1 per world (revisits: by distance to the nearest map scan, 4-5 / 5-6 /
6-7 / 7-8 m) and the correct top-1s whose yaw is off by more than 10 degrees. --time
prints the median time per query of `match_queries` today and with the `TIMED` views
(their re-centring and signatures included), interleaved in this process, on the first
world.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]


def y_offsets(*metres: float, x: bool = False) -> np.ndarray:
    pos = [(0.0, s * m) for m in metres for s in (1, -1)]
    if x:
        pos += [(s * m, 0.0) for m in metres for s in (1, -1)]
    return np.array(pos, np.float32)


# name: (kind, positions, gate, penalty, factor). With a gate, a query takes today's
# answer unless its re-rank distance is above the gate; penalty is added to a view's
# re-rank distance, and a view's signature distance is multiplied by factor; keep_own
# (`own`) keeps today's candidates in the wider pass (QueryViewIndex).
VARIANTS: dict[str, tuple] = {
    "today": ("none", None),
    "map sv5": ("map", None),
    "G y4": ("G", y_offsets(4.0)),
    "G y5": ("G", y_offsets(5.0)),
    "G y4-6": ("G", y_offsets(4.0, 5.0, 6.0)),
    "G xy5": ("G", y_offsets(5.0, x=True)),
    "U y5": ("U", y_offsets(5.0)),
    "G+U y5": ("GU", y_offsets(5.0)),
    "G+U y4-6": ("GU", y_offsets(4.0, 5.0, 6.0)),
    "G+U xy5": ("GU", y_offsets(5.0, x=True)),
    "G+U y4-6 +0.03": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.03),
    "G+U y4-6 +0.05": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.05),
    "G+U y5 x1.05": ("GU", y_offsets(5.0), None, 0.0, 1.05),
    "G+U y5 x1.1": ("GU", y_offsets(5.0), None, 0.0, 1.1),
    "G+U y4-6 x1.05": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.0, 1.05),
    "G+U y4-6 x1.1": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.0, 1.1),
    "G+U y4-6 +0.03 x1.05": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.03, 1.05),
    "G+U y5 own": ("GU", y_offsets(5.0), None, 0.0, 1.0, True),
    "G+U y4-6 own": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.0, 1.0, True),
    "G+U y4-6 +0.03 own": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.03, 1.0, True),
    "G+U y4-6 +0.03 x1.05 own": ("GU", y_offsets(4.0, 5.0, 6.0), None, 0.03, 1.05, True),
    "G+U y5 if r>0.6": ("GU", y_offsets(5.0), 0.6),
    "G+U y4-6 if r>0.5": ("GU", y_offsets(4.0, 5.0, 6.0), 0.5),
    "G+U y4-6 if r>0.6": ("GU", y_offsets(4.0, 5.0, 6.0), 0.6),
}


class QueryViewIndex:
    """`SignatureIndex.search` over the map scans for queries given as V signatures each
    ([b, V * D], the query's own first): each scan at its nearest over the views, a
    view's distances multiplied by `factor` (>= 1: a view must be that much nearer).
    With `keep_own`, the k nearest by the query's own signature are returned too (up to
    2k rows, by distance): the wider re-ranking pass then sees today's candidates."""

    def __init__(self, signatures: np.ndarray, factor: float = 1.0, keep_own: bool = False):
        from disco_cli.query.search import SignatureIndex

        self.inner = SignatureIndex(signatures)
        self.dim, self.factor, self.keep_own = self.inner.dim, factor, keep_own

    def __len__(self) -> int:
        return len(self.inner)

    def search(self, queries, k, limit=None, exclude=None):
        q = np.atleast_2d(np.asarray(queries, np.float32))
        b, v = len(q), q.shape[1] // self.dim
        rows, dists = self.inner.search(q.reshape(b * v, self.dim), k)
        dists = dists.reshape(b, v, k) * np.r_[1.0, np.full(v - 1, self.factor)][None, :, None]
        rows, dists = rows.reshape(b, v * k), dists.reshape(b, v * k)
        width = 2 * k if self.keep_own else k
        out_r = np.full((b, width), -1, np.int64)
        out_d = np.full((b, width), np.inf)
        for i in range(b):
            o = np.argsort(dists[i], kind="stable")
            r, d = rows[i][o], dists[i][o]
            keep = r >= 0
            r, d = r[keep], d[keep]
            _, first = np.unique(r, return_index=True)
            first = np.sort(first)
            if self.keep_own:
                first = first[np.isin(r[first], rows[i, :k]) | (np.arange(len(first)) < k)]
            else:
                first = first[:k]
            out_r[i, : len(first)], out_d[i, : len(first)] = r[first], d[first]
        return out_r, out_d


class ViewReranked:
    """The model with re-rank distances the smallest over the query's U re-centred at
    `positions` (and its own); `views` set per query before each search."""

    def __init__(self, base, penalty: float = 0.0):
        self.base, self.penalty = base, penalty
        self.views: np.ndarray | None = None

    def __getattr__(self, name):
        return getattr(self.base, name)

    def rerank_distances(self, query_features, candidate_features):
        from disco_cli.model.verify import aligned_correlation

        cands = self.base._u(np.asarray(candidate_features))
        best = 1.0 - aligned_correlation(self.base._u(query_features), cands)
        for u in self.views:
            best = np.minimum(best, 1.0 + self.penalty - aligned_correlation(u, cands))
        return best.astype(np.float32)


def g_views(model, qf: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """The signatures [1, (1 + V) * D] of one query: its own, then its G re-centred."""
    from disco_cli.model.signature import signatures
    from disco_cli.model.yaw_refine import recentre

    g = model._g(qf)
    views = recentre(g, positions, model.bev_config.max_range)
    return signatures(np.concatenate([g[None], views]), model.crop).reshape(1, -1)


def bev_views(model, points: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(signatures, features) of the views embedded again from the query's points
    re-centred."""
    from disco_cli.model.bev import polar_bev

    bevs = []
    for x, y in positions:
        p = np.array(points, np.float32, copy=True)
        p[:, 0] -= x
        p[:, 1] -= y
        bevs.append(polar_bev(p, model.bev_config))
    return model.embed(np.stack(bevs).astype(np.float32))


class World:
    def __init__(self, spec: str, cache: Path, model):
        import revisit_rerank_probe as rr

        from disco_cli.maps.database import MatchRows

        world, radius = spec.rsplit(":", 1)
        self.path, self.radius = Path(world), float(radius)
        self.e = e = rr.embedded(self.path, cache, model)
        mp, q = e["mpose"], e["qxyyaw"]
        self.true_d = np.hypot(mp[None, :, 0] - q[:, None, 0], mp[None, :, 1] - q[:, None, 1])
        self.has = np.flatnonzero(self.true_d.min(axis=1) <= self.radius)
        paths = [f"scan{i}" for i in range(len(mp))]

        class Memory:
            def rows(self, ids):
                ids = np.asarray(ids, np.int64)
                return MatchRows(ids, [paths[i] for i in ids], mp[ids], e["mf"][ids])

        self.db, self.ids = Memory(), np.arange(len(mp))

    def query_points(self, i: int) -> np.ndarray:
        import json

        import ood_suite as suite

        if not hasattr(self, "_queries"):
            seed = int(json.loads((self.path / "world.json").read_text())["seed"])
            qp, qpose = suite.load_session(self.path / "01")
            self._queries = suite.Queries(qp, qpose, 0.0, seed=seed)
        return self._queries.points(i)

    def run(
        self,
        model,
        kind: str,
        positions,
        gate=None,
        penalty=0.0,
        factor=1.0,
        keep_own=False,
        policy=None,
    ) -> tuple[float, int, list[float], int]:
        """Recall@1 of one variant; `policy`: the query stage's for `kind` "none" (default:
        the model's without its own views, as before they were built)."""
        from disco_cli.maps.map_side_views import ViewIndex
        from disco_cli.query.search import SignatureIndex, match_queries

        e = self.e
        if kind == "map":
            sel = np.flatnonzero(np.isclose(np.abs(e["offs"]), 5.0))
            n = len(e["ms"])
            index = ViewIndex(
                e["ms"], np.repeat(np.arange(n), len(sel)), e["vs"][:, sel].reshape(-1, 1024)
            )
        elif kind == "none":
            index = SignatureIndex(e["ms"])
        else:
            index = QueryViewIndex(e["ms"], factor, keep_own)
        m = ViewReranked(model, penalty) if kind in ("U", "GU", "bevF") else model
        # The probe makes its own views: the shipped ones (built after it) stay off.
        no_views = replace(model.query_policy, view_offsets=())
        if kind == "none" and policy is not None:
            no_views = policy
        plain = SignatureIndex(e["ms"])
        hits, near, over10 = [], [], 0
        for i in self.has:
            qf = e["qf"][i : i + 1]
            if gate is not None:
                best = match_queries(
                    plain, self.ids, self.db, model, e["qs"][i : i + 1], qf, 1, no_views
                )
                best = best[0][0]
                if best.distance <= gate:
                    self._score(i, best, hits, near)
                    continue
            if kind in ("G", "GU"):
                sig = g_views(model, qf[0], positions)
            elif kind in ("bev", "bevF"):
                vs, vf = bev_views(model, self.query_points(i), positions)
                sig = np.concatenate([e["qs"][i : i + 1], vs]).reshape(1, -1)
                if kind == "bevF":
                    m.views = model._u(vf)
            else:
                sig = e["qs"][i : i + 1]
            if kind in ("U", "GU"):
                from disco_cli.model.yaw_refine import recentre

                m.views = recentre(model._u(qf[0]), positions, model.bev_config.max_range)
            best = match_queries(index, self.ids, self.db, m, sig, qf, 1, no_views)[0][0]
            over10 += self._score(i, best, hits, near)
        hits, near = np.array(hits), np.array(near)
        bands = [(near >= a) & (near < a + 1) for a in (4, 5, 6, 7)]
        by = [float(hits[b].mean()) if b.any() else float("nan") for b in bands]
        return float(hits.mean()), len(hits), by, over10

    def _score(self, i: int, best, hits: list, near: list) -> int:
        """Appends query i's hit and distance; 1 if a hit's yaw is off by over 10 deg."""
        hit = self.true_d[i, best.row] <= self.radius
        hits.append(hit)
        near.append(self.true_d[i].min())
        if not hit:
            return 0
        true = math.degrees(self.e["qxyyaw"][i, 2] - self.e["mpose"][best.row, 3])
        return int(abs((best.yaw_deg - true + 180.0) % 360.0 - 180.0) > 10.0)


TIMED = ("G+U y5", "G+U y4-6 +0.03 own")


def time_views(w: World, model, reps: int = 3) -> None:
    """Median time per query of `match_queries` today and with the TIMED query-side
    views (the re-centred images and their signatures included), interleaved."""
    from disco_cli.model.yaw_refine import recentre
    from disco_cli.query.search import SignatureIndex, match_queries

    e, rng = w.e, model.bev_config.max_range
    plain = SignatureIndex(e["ms"])
    runs = []
    for name in TIMED:
        _, pos, _, penalty, factor, keep_own = (
            VARIANTS[name] + (None, 0.0, 1.0, False)[len(VARIANTS[name]) - 2 :]
        )
        runs.append(
            (name, pos, QueryViewIndex(e["ms"], factor, keep_own), ViewReranked(model, penalty))
        )
    no_views = replace(model.query_policy, view_offsets=())  # the probe's own views only
    times: dict[str, list[float]] = {"today": [], **{name: [] for name in TIMED}}
    for _ in range(reps):
        for i in range(len(e["qs"])):
            qf = e["qf"][i : i + 1]
            t = time.perf_counter()
            match_queries(plain, w.ids, w.db, model, e["qs"][i : i + 1], qf, 10, no_views)
            times["today"].append(time.perf_counter() - t)
            for name, pos, index, m in runs:
                t = time.perf_counter()
                sig = g_views(model, qf[0], pos)
                m.views = recentre(model._u(qf[0]), pos, rng)
                match_queries(index, w.ids, w.db, m, sig, qf, 10, no_views)
                times[name].append(time.perf_counter() - t)
    med = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    print(
        f"match_queries per query ({w.path.name}, {len(e['ms'])} map scans, median of "
        f"{len(times['today'])}, interleaved): "
        + ", ".join(
            f"{name} {ms:.2f} ms" + (f" (x{ms / med['today']:.2f})" if name != "today" else "")
            for name, ms in med.items()
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("worlds", nargs="+", help="WORLD:RADIUS")
    ap.add_argument("--cache", type=Path, default=Path("out/qsv"))
    ap.add_argument("--bev", action="store_true", help="add BEV y5 (one U-Net pass per view)")
    ap.add_argument("--time", action="store_true", help="time today against G y5, first world")
    args = ap.parse_args()
    from _common import print_header

    print_header("query_side_views_probe")
    import torch

    torch.set_num_threads(2)
    from disco_cli.model import load_model

    model = load_model("default")
    if args.time:
        time_views(World(args.worlds[0], args.cache, model), model)
        return
    variants = dict(VARIANTS)
    if args.bev:
        variants["BEV y5"] = ("bev", y_offsets(5.0))
        variants["BEV+U y5"] = ("bevF", y_offsets(5.0))
    print("| world | queries | " + " | ".join(variants) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in variants) + " |")
    for spec in args.worlds:
        w = World(spec, args.cache, model)
        cells, n = [], 0
        for v in variants.values():
            r1, n, by, over10 = w.run(model, *v)
            cell = f"{r1:.3f}"
            if w.radius > 5:
                cell += " (" + " / ".join(f"{b:.2f}" for b in by) + ")"
            cells.append(cell + (f" [{over10}]" if over10 else ""))
        print(f"| {w.path.name} | {n} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
