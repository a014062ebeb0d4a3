"""How far apart a signature keeps places: the margin that a saturated Recall@1 hides.

    .venv/bin/python docs/research/probes/signature_margin.py [--models default spectral PATH.pt]
    .venv/bin/python docs/research/probes/signature_margin.py --worlds sel/s5001 sel/s5007 \\
        [--models ...]

Where every model finds 99-100 % of the queries (the suite's worlds with revisits up to
1.5 m to the side), Recall@1 cannot say which signature is nearer to losing a place.
For each query of a suite world that has a true match (a map scan within 5 m), this
takes the signature distance to its nearest true map scan, d_true, and to the nearest
map scan more than 20 m away (another place), d_other, and reports the ratio
d_other / d_true: above 1 the true place is the nearer signature, and the closer to 1,
the less it takes to lose it. The signature alone, as the search ranks it (L2, no
re-ranking): a query lost here may still be saved by re-ranking the 10 nearest.

It reads the worlds that `benchmarks/run_ood.sh` made under out/ood/worlds (missing ones
are skipped, not simulated) and caches each (world, model) under out/ood/margin, keyed
by the model's fingerprint. Per group, beam count and change level, pooled over the
held-out styles, it prints the median ratio, its 10th percentile, the share of close
calls (ratio below 1.1) and the share lost on the signature alone (below 1). With
--worlds it reads any `disco simulate` folders instead (model selection's), one row
each, uncached.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# Beside the dated notes; ood_suite and _common stay in benchmarks/ (the repository root
# is three folders up), sibling probes import each other from here.
sys.path[:0] = [
    str(Path(__file__).resolve().parent),
    str(Path(__file__).resolve().parents[3] / "benchmarks"),
]

CLOSE = 1.1  # a ratio below this is a close call
FAR = 20.0  # another place: a map scan farther than this (m) from the query


def margin_ratios(world, radius: float, far: float) -> np.ndarray:
    """d_other / d_true for each query of `world` (an `ood_suite.EmbeddedWorld`) that has
    a map scan within `radius` and one beyond `far`."""
    from disco_cli.io.poses import xy_yaw

    mx, my, _ = xy_yaw(world.map_poses)
    qx, qy, _ = xy_yaw(world.queries.poses)
    metres = np.hypot(qx[:, None] - mx[None], qy[:, None] - my[None])
    ms = world.map_signatures.astype(np.float64)
    qs = world.query_signatures.astype(np.float64)
    sq = (qs * qs).sum(1)[:, None] + (ms * ms).sum(1)[None] - 2.0 * qs @ ms.T
    dist = np.sqrt(np.maximum(sq, 0.0))
    d_true = np.where(metres <= radius, dist, np.inf).min(1)
    d_other = np.where(metres > far, dist, np.inf).min(1)
    keep = np.isfinite(d_true) & np.isfinite(d_other)
    # A query whose signature equals its true match's is as safe as it gets.
    return d_other[keep] / np.maximum(d_true[keep], 1e-12)


def cached_ratios(out: Path, world_name: str, model, key: str, compute) -> np.ndarray:
    """The ratios of one (suite world, model), computed once per model fingerprint."""
    f = out / f"{world_name}--{key}.json"
    head = {"world": world_name, "fingerprint": model.fingerprint, "far": FAR}
    if f.is_file():
        data = json.loads(f.read_text())
        if data.get("head") == head:
            return np.asarray(data["ratios"], np.float64)
    ratios = compute()
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".partial")
    tmp.write_text(json.dumps({"head": head, "ratios": [round(float(r), 5) for r in ratios]}))
    tmp.replace(f)
    return ratios


def summary(ratios: np.ndarray) -> str:
    if not len(ratios):
        return "- | - | - | -"
    return (
        f"{np.median(ratios):.2f} | {np.percentile(ratios, 10):.2f} "
        f"| {np.mean(ratios < CLOSE):.3f} | {np.mean(ratios < 1.0):.3f}"
    )


def print_table(first: list[str], rows: list[tuple[list[str], list[np.ndarray]]], models) -> None:
    """A Markdown table: the `first` columns, then four per model (see `summary`)."""
    cols = first + [f"{k} {c}" for k in models for c in ("median", "p10", f"<{CLOSE:g}", "<1")]
    print("| " + " | ".join(cols) + " |")
    print("| --- | " + " | ".join("---:" for _ in cols[1:]) + " |")
    for cells, per_model in rows:
        print("| " + " | ".join(cells + [summary(r) for r in per_model]) + " |", flush=True)


def folder_rows(folders: list[Path], models, threads: int):
    """One row per `disco simulate` folder (model selection's worlds), uncached."""
    import ood_suite as suite

    for folder in folders:
        per_model = [
            margin_ratios(suite.embed_world(m, folder, 0.0, threads), suite.RADIUS, FAR)
            for m in models.values()
        ]
        yield [folder.name, str(len(per_model[0]))], per_model


def suite_rows(root: Path, only: list[str], models, threads: int):
    """One row per group, beam count and change level of the suite, pooled over styles."""
    import ood_suite as suite

    caps = {"change": True, "styles": list(suite.HELD_OUT_STYLES), "offset": True, "tilt": True}
    worlds = [w for w in suite.plan_worlds(False, caps)[0] if any(o in w.name for o in only)]
    present = [w for w in worlds if (root / "worlds" / w.name / "world.json").is_file()]
    if len(present) < len(worlds):
        print(f"{len(worlds) - len(present)} suite worlds absent under {root}/worlds, skipped")
    ratios = {}
    for w in present:
        folder = root / "worlds" / w.name
        for key, model in models.items():
            ratios[(w.name, key)] = cached_ratios(
                root / "margin",
                w.name,
                model,
                key,
                lambda m=model, f=folder, t=w.tilt_deg: margin_ratios(
                    suite.embed_world(m, f, t, threads), suite.RADIUS, FAR
                ),
            )
    titles = {"grid": "held-out towns", "hard": "hard set", "stress": "stress"}
    rows = []
    for group in ("grid", "hard", "stress"):
        gw = [w for w in present if w.group == group]
        for beams, c in sorted({(w.beams, w.change) for w in gw}):
            sel = [w for w in gw if (w.beams, w.change) == (beams, c)]
            per_model = [np.concatenate([ratios[(w.name, k)] for w in sel]) for k in models]
            rows.append(
                ([f"{titles[group]}, {beams} beams", f"{c:.2f}", str(len(per_model[0]))], per_model)
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=["default", "spectral"])
    ap.add_argument("--out", type=Path, default=None, help="the suite's folder (out/ood)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--only", default="", help="worlds whose name contains one of these (,)")
    ap.add_argument("--worlds", nargs="+", type=Path, help="other worlds than the suite's")
    args = ap.parse_args(argv)

    import ood_suite as suite
    import torch
    from _common import print_header

    from disco_cli.model import load_model

    torch.set_num_threads(args.threads)
    print_header("signature_margin")
    models = {suite.model_key(m): load_model(m) for m in args.models}
    print(
        f"\nd_other / d_true: signature distance to the nearest map scan beyond {FAR:g} m over "
        f"that to the nearest within {suite.RADIUS:g} m; median, 10th percentile, share "
        f"below {CLOSE:g} (close calls), share below 1 (lost before re-ranking)\n"
    )
    if args.worlds:
        print_table(
            ["world", "queries"], list(folder_rows(args.worlds, models, args.threads)), models
        )
        return 0
    root = args.out or suite.ROOT / "out" / "ood"
    only = [o for o in args.only.split(",") if o] or [""]
    print_table(
        ["worlds", "change", "queries"], suite_rows(root, only, models, args.threads), models
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
