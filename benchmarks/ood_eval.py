"""Any two-session worlds with the out-of-distribution suite's protocol, queries optionally
tilted or shifted in z: how model selection and the tilt measurement of
docs/research/model-history.md ran.

    .venv/bin/python benchmarks/ood_eval.py WORLD... --models default ft.pt [--tilt 3] [--z 0.5]
        [--rerank-wider 0] [--snap-radius 0] [--rerank 0] [--radius 8.5]
        [--policy FIELD=VALUE ...]

`NAME+svM` is NAME with a map of side views M m to each side, `spectral+snap` the floor
searched with the network's snap to the nearest map scan (as in ood_suite.py).

Each WORLD holds sessions 00 (the map) and 01 (the queries); a match is true within 5 m
(`--radius`: 8.5 for revisits 4-8 m to the side, then also Recall@1 by distance).
Prints one line per model: Recall@1 / Recall@5 / mean yaw error (deg) and the misses of
Recall@1 per world. `--rerank-wider 0 --snap-radius 0` gives the network's search as it
was before those two steps. `--policy` sets any field of the query stage's `QueryPolicy`
(disco_cli/query/query_policy.py) for an ablation, e.g. `--policy signature_weight=0
view_offsets= yaw_check_below=0` (a tuple as comma-separated numbers, empty for none).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ood_suite as S  # noqa: E402


class _Lift:
    """Queries moved by dz metres in z (another mounting height); no rotation."""

    def __init__(self, dz: float):
        self.dz = dz

    def rotation(self, i: int) -> np.ndarray:
        return np.eye(4)

    def __call__(self, pts: np.ndarray, i: int) -> np.ndarray:
        from disco_cli.training.augment import shift_z

        return shift_z(pts, self.dz)


def with_fields(policy, settings: list[str]):
    """`policy` with FIELD=VALUE settings, each VALUE read as the field's type."""
    from dataclasses import fields, replace

    from disco_cli.errors import DiscoError

    types = {f.name: type(getattr(policy, f.name)) for f in fields(policy)}
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep or key not in types:
            raise SystemExit(f"--policy {item}: FIELD=VALUE with FIELD one of {', '.join(types)}")
        kind = types[key]
        try:
            if kind is tuple:
                new = tuple(float(v) for v in value.split(",") if v.strip())
            else:
                new = kind(float(value)) if kind is int else kind(value)
            policy = replace(policy, **{key: new})  # QueryPolicy checks the value's range
        except (DiscoError, ValueError, OverflowError) as exc:
            raise SystemExit(f"--policy {item}: {exc}") from None
    return policy


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("worlds", nargs="+", type=Path)
    ap.add_argument("--models", nargs="+", default=["default", "spectral"])
    ap.add_argument("--tilt", type=float, default=0.0, help="queries' roll and pitch within +-DEG")
    ap.add_argument("--z", type=float, default=0.0, help="queries shifted by this (m)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the tilts")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--rerank-wider", type=int, help="the network's wider pass depth (0: none; as the CLI)"
    )
    ap.add_argument("--snap-radius", type=float, help="the network's snap radius (0: none)")
    ap.add_argument("--rerank", type=int, help="candidates re-ranked (0: none; as the CLI)")
    ap.add_argument(
        "--radius",
        type=float,
        default=S.RADIUS,
        help="a match is true within this (m); above 5, Recall@1 by distance too (revisits)",
    )
    ap.add_argument(
        "--policy",
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="QueryPolicy fields to set (an ablation), e.g. signature_weight=0 view_offsets=",
    )
    args = ap.parse_args()

    import torch

    from disco_cli.query.query_policy import policy_for

    torch.set_num_threads(args.threads)
    for name in args.models:
        side_views = S.split_side_views(name)[1]
        model = S.load_suite_model(name)
        # The settings given, where the model has the rule (a QueryPolicy; the model's
        # own is never changed).
        p = model.query_policy
        wider = args.rerank_wider if p.rerank_wider else None
        snap = args.snap_radius if model.abilities.locate else None
        rerank = args.rerank if model.abilities.rerank else None
        policy = policy_for(model, rerank=rerank, rerank_wider=wider, snap_radius=snap)
        policy = with_fields(policy, args.policy)
        print(f"{name}: {policy}", flush=True)
        cells = []
        for w in args.worlds:
            mp, mpose = S.load_session(w / "00")
            qp, qpose = S.load_session(w / "01")
            tf = _Lift(args.z) if args.z else None
            q = S.Queries(qp, qpose, args.tilt, seed=args.seed, transform=tf)
            rows = S.evaluate(
                model, mp, mpose, q, args.threads, side_views, radius=args.radius, policy=policy
            )
            s = S.summarize(rows)
            has = [r for r in rows if r["has"]]
            miss = sum(not r["r1"] for r in has)
            bins = ""
            if args.radius > S.RADIUS:
                for lo, hi in S.REVISIT_BINS[1:-1]:
                    sel = [r["r1"] for r in has if lo <= r["near_m"] < hi]
                    bins += f" {lo:g}-{hi:g} m {np.mean(sel):.2f} ({len(sel)})" if sel else ""
            cells.append(
                f"{w.name} {s['r1']:.3f} / {s['r5']:.3f} / {s['yaw_mean']:.2f} "
                f"({miss} of {len(has)} missed; {s['yaw_over10']} yaw > 10 deg){bins}"
            )
        print(S.model_key(name), " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
