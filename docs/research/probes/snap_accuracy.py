"""How well the snap to the nearest map scan knows where the query is, on simulated worlds.

    .venv/bin/python docs/research/probes/snap_accuracy.py [WORLD ...] [--model default]

For each world (default: every world of the suite cached in out/ood/worlds; each holds
sessions 00, the map, and 01, the queries), the queries are searched as `disco query`
does, once without the snap and once with it. Printed, over the queries whose best match
before the snap lies within 5 m (a true match):

- the error of the query's position estimated from that best match
  (`search.query_on_map_conf`, what the snap uses): median, 90th and 99th percentile, max;
- how often the snap moves the best match, and how far (median, on the map);
- Recall@1 (a match within 5 m) without and with the snap; with --list, each query it
  finds or loses: how far the best match lay, and where the true one was.

docs/research/model-history.md, "Snapping to the nearest map scan", quotes these figures.
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
import ood_suite as S  # noqa: E402

RADIUS = 5.0


class _MapRows:
    """The map's features and poses, standing in for a database in `match_queries`."""

    def __init__(self, world: S.EmbeddedWorld, pose4: np.ndarray):
        self.world, self.pose4 = world, pose4

    def rows(self, ids: np.ndarray):
        from disco_cli.maps.database import MatchRows

        ids = np.asarray(ids, np.int64)
        paths = [str(self.world.map_paths[i]) for i in ids]
        return MatchRows(ids, paths, self.pose4[ids], self.world.map_features[ids])


def measure(model, policy, world: S.EmbeddedWorld, name: str) -> dict[str, list]:
    from disco_cli.io.poses import xy_yaw
    from disco_cli.query.search import SignatureIndex, match_queries, query_on_map_conf

    mx, my, myaw = xy_yaw(world.map_poses)
    qx, qy, _ = xy_yaw(world.queries.poses)
    pose4 = np.c_[mx, my, world.map_poses[:, 2, 3], myaw]
    store, index = _MapRows(world, pose4), SignatureIndex(world.map_signatures)
    ids = np.arange(len(mx))
    qs, qf = world.query_signatures, world.query_features

    def search(snap: float, k: int) -> list:
        p = replace(policy, refine_yaw=0, snap_radius=snap)
        return match_queries(index, ids, store, model, qs, qf, k, p)

    plain = search(0.0, 10)
    before, after = [m[0].row for m in plain], [m[0].row for m in search(policy.snap_radius, 1)]
    out: dict[str, list] = {"err": [], "moved": [], "move_m": [], "hit0": [], "hit1": []}
    out["changed"] = []
    for i, (b, a) in enumerate(zip(before, after)):
        d = np.hypot(mx - qx[i], my - qy[i])
        if d.min() > RADIUS:
            continue
        out["hit0"].append(d[b] <= RADIUS)
        out["hit1"].append(d[a] <= RADIUS)
        if (d[b] <= RADIUS) != (d[a] <= RADIUS):
            true = [j for j, m in enumerate(plain[i]) if d[m.row] <= RADIUS]
            where = (
                f"the true one ranked {true[0] + 1} of 10, re-ranked "
                f"{plain[i][true[0]].distance - plain[i][0].distance:+.3f} from the best"
                if true
                else "no true match among the 10 best"
            )
            out["changed"].append(
                f"{name} query {i}: nearest map scan "
                f"{d.min():.2f} m; best match {d[b]:.2f} m before the snap, {d[a]:.2f} m "
                f"after; {where}"
            )
        out["moved"].append(a != b)
        if a != b:
            out["move_m"].append(math.hypot(mx[a] - mx[b], my[a] - my[b]))
        if d[b] <= RADIUS:
            _, (ex, ey), _ = query_on_map_conf(model, qf[i], world.map_features[b], pose4[b])
            out["err"].append(math.hypot(ex - qx[i], ey - qy[i]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("worlds", nargs="*", type=Path)
    ap.add_argument("--model", default="default")
    ap.add_argument("--out", type=Path, default=S.ROOT / "out" / "ood")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--list", action="store_true", help="each query the snap finds or loses")
    ap.add_argument("--radius", type=float, help="snap radius (m); default the model's")
    ap.add_argument("--margin", type=float, help="snap margin; default the model's")
    args = ap.parse_args()

    import torch
    from _common import print_header

    from disco_cli.model import load_model

    torch.set_num_threads(args.threads)
    worlds = args.worlds or sorted(p.parent for p in (args.out / "worlds").glob("*/world.json"))
    if not worlds:
        raise SystemExit(f"no worlds given and none cached in {args.out / 'worlds'}")
    model = load_model(args.model)
    policy = model.query_policy
    if not policy.snap_radius:
        raise SystemExit(f"model {model.name} does not snap")
    if args.radius is not None:
        policy = replace(policy, snap_radius=args.radius)
    if args.margin is not None:
        policy = replace(policy, snap_margin=args.margin)
    print_header("snap_accuracy")
    total: dict[str, list] = {}
    for w in worlds:
        got = measure(model, policy, S.embed_world(model, w, threads=args.threads), w.name)
        for k, v in got.items():
            total.setdefault(k, []).extend(v)
        print(f"  {w.name}: {len(got['hit0'])} queries", file=sys.stderr, flush=True)
    err = np.array(total["err"])
    p50, p90, p99 = np.percentile(err, [50, 90, 99])
    n = len(total["hit0"])
    moved = int(np.sum(total["moved"]))
    print(
        f"{args.model} (snap within {policy.snap_radius:g} m, margin {policy.snap_margin:g}), "
        f"{len(worlds)} worlds, {n} queries with a true match within 5 m:\n"
        f"  position estimated from a true best match ({len(err)}): error median {p50:.2f} m, "
        f"p90 {p90:.2f}, p99 {p99:.2f}, max {err.max():.2f}\n"
        f"  the snap moved the best match for {moved} ({100 * moved / n:.0f} %), by a median "
        f"{np.median(total['move_m']) if moved else 0:.2f} m on the map\n"
        f"  Recall@1 without the snap {np.mean(total['hit0']):.4f} "
        f"({n - int(np.sum(total['hit0']))} missed), with it {np.mean(total['hit1']):.4f} "
        f"({n - int(np.sum(total['hit1']))} missed)"
    )
    if args.list:
        print("\n".join(f"  {line}" for line in total["changed"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
