"""Fit the confidence of query/confidence.py on the selection worlds, and judge it.

    benchmarks/calibrate_confidence.py collect [--families nclt mulran oxford]
    benchmarks/calibrate_confidence.py fit [--write] [--plot]
    benchmarks/calibrate_confidence.py loops

`collect` runs every query of the calibrated families' selection worlds (seeds
8621-8623, `evaluation/paper_families.py`; the worlds `benchmarks/paper_table.py`
simulates, under out/paper/worlds) through `Map.query` with the shipped model and its
query rule, unverified, and records for each of its best 10 rows the place cues
(`confidence.PlaceCues`), the yaw confidence and whether it is a true revisit (within the
family's radius of the query's true position); the best `CHECK_DEPTH` rows also get
the layout check (`relative_pose.layout_check`: peak, shift, flipped) and the best
`ICP_DEPTH` the ICP (`relative_pose.estimate_relative_pose`: fitness, rmse, accepted),
each with its time. Rows are cached as JSON lines under out/confidence/.

`fit` fits a logistic model on those rows per kind of evidence (`KINDS`: the place
cues alone; with the layout check) by Newton's method on the log-loss with a small
ridge, leaving one world out in turn to say what each cue adds (the held-out log-loss
with the cue and without it) and how well the predicted probability matches the
observed share in bins. `--write` stores the coefficients in
src/disco_cli/query/confidence_fit.json, which the package loads. `loops` gives the
precision and recall of each confidence bar for the default loop detector.

Only selection seeds are fitted on; `collect --seeds report` is for the report, after.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from disco_cli.evaluation.paper_families import (
    FAMILIES,
    SEEDS,
    labelled_xy,
    load_run,
    scan_points,
)
from disco_cli.io.poses import xy_yaw
from disco_cli.maps.facade import Map
from disco_cli.query import relative_pose
from disco_cli.query.confidence import PlaceCues, cue_features
from disco_cli.query.relative_pose import LayoutCheck

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "confidence"
FIT_FILE = ROOT / "src" / "disco_cli" / "query" / "confidence_fit.json"
TOPK = 10
CHECK_DEPTH = 3  # rows given the layout check (relative_pose.layout_check)
ICP_DEPTH = 1  # rows given the ICP of estimate_relative_pose (--pose)


def world(seed: int, fam: str) -> Path:
    folder = ROOT / "out" / "paper" / "worlds" / f"{fam}-{seed}"
    if not (folder / "world.json").is_file():
        sys.exit(f"{folder}: not simulated; run benchmarks/paper_table.py --seeds ... first")
    return folder


def timed(fn, *args):
    """fn(*args), and the milliseconds it took (to 0.01 ms)."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, round(1000 * (time.perf_counter() - t0), 2)


def collect(fam_name: str, seed: int) -> Path:
    fam = FAMILIES[fam_name]
    out = OUT / f"{fam_name}-{seed}.jsonl"
    if out.is_file():
        return out
    folder = world(seed, fam_name)
    meta = json.loads((folder / "world.json").read_text())
    mount = float(meta["sensor"]["mount_height"])
    map_paths, map_poses = load_run(folder / "00")
    q_paths, q_poses = load_run(folder / "01")
    mx, my, _ = xy_yaw(map_poses)
    qx, qy, qyaw = xy_yaw(q_poses)
    qx, qy = labelled_xy(fam, qx, qy, qyaw)
    row_of = {str(p): i for i, p in enumerate(map_paths)}
    map_points = {}
    lines = []
    t0 = time.monotonic()
    db = OUT / "maps" / f"{fam_name}-{seed}.db"
    db.parent.mkdir(parents=True, exist_ok=True)
    if not db.is_file():
        m = Map.create(db.with_suffix(".partial"), "default")
        m.add_many(
            (scan_points(fam, p, mount, i), str(p), map_poses[i]) for i, p in enumerate(map_paths)
        )
        m.close()
        db.with_suffix(".partial").replace(db)
    with Map.open(db) as m:
        unchecked = replace(m.model.query_policy, check_candidates=0)
        for i, p in enumerate(q_paths):
            if i % fam.query_every:
                continue
            pts = scan_points(fam, p, mount, 10**6 + i)
            matches = m.query(pts, topk=TOPK, name=str(p), policy=unchecked)
            d_all = np.hypot(mx - qx[i], my - qy[i])
            rows = []
            for j, mt in enumerate(matches):
                k = row_of[mt.name]
                c = mt.cues
                row = {
                    "rank": j + 1,
                    "true": bool(d_all[k] <= fam.radius),
                    "metres": round(float(d_all[k]), 2),
                    "distance": c.distance,
                    "rerank": c.rerank,
                    "rerank_own": c.rerank_own,
                    "signature": c.signature,
                    "lead": c.lead,
                    "yaw_conf": mt.yaw_conf if mt.yaw_conf is not None else math.nan,
                }
                if j < CHECK_DEPTH:
                    if k not in map_points:
                        map_points[k] = scan_points(fam, map_paths[k], mount, k)
                    lc, ms = timed(relative_pose.layout_check, pts, map_points[k], mt.yaw_deg)
                    row.update(peak=lc.peak, shift_m=lc.shift_m, flipped=lc.flipped, check_ms=ms)
                if j < ICP_DEPTH:
                    icp = relative_pose.estimate_relative_pose
                    rp, ms = timed(icp, pts, map_points[k], mt.yaw_deg)
                    row.update(fitness=rp.fitness, rmse=rp.rmse, accepted=rp.accepted, icp_ms=ms)
                rows.append(row)
            has = bool(d_all.min() <= fam.radius)
            lines.append(json.dumps({"query": i, "has": has, "rows": rows}, allow_nan=True))
    OUT.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".partial").write_text("\n".join(lines) + "\n")
    out.with_suffix(".partial").replace(out)
    print(f"  {out.name}: {len(lines)} queries, {time.monotonic() - t0:.0f} s", file=sys.stderr)
    return out


# -- the logistic fit ---------------------------------------------------------------------

# Every cue the query gives, per amount of evidence: `fit` says what each adds.
PLACE = ["rerank", "log_signature", "lead", "yaw_conf", "view_gain"]
CHECKED = PLACE + ["peak", "shift", "flipped"]
POSED = CHECKED + ["fitness", "rmse"]
CANDIDATES = {"place": PLACE, "checked": CHECKED, "posed": POSED}
# What the shipped calibrations weigh: the cues whose removal did not improve the
# held-out log-loss (each world predicted by a fit on the others), by backward
# elimination on the selection worlds (docs/confidence.md). The ICP fit's cues did not
# carry from one family to another, so a pose adds none: rows with a pose get the
# `checked` confidence.
# `lead` and `flipped` were left out by hand though they lowered it by 0.001-0.002: the
# first stands on map poses a sequence may lack, the second on which way the families'
# runs happened to drive (configurations tried: docs/confidence.md).
KINDS = {
    "place": ["rerank", "yaw_conf", "view_gain"],
    "checked": ["rerank", "yaw_conf", "view_gain", "peak", "shift"],
}
NEEDS = {"place": None, "checked": "peak", "posed": "fitness"}


def features(row: dict, names: list[str]) -> list[float]:
    """The row's features as query/confidence.py computes them (`cue_features`)."""
    cues = PlaceCues(
        row["distance"], row["rerank"], row["rerank_own"], row["signature"], row["lead"]
    )
    layout = None
    if "peak" in names:
        layout = LayoutCheck(row["peak"], row["shift_m"], row["flipped"])
    fit = row.get("fitness", math.nan) if "fitness" in names else math.nan
    rmse = row.get("rmse", math.nan) if "fitness" in names else math.nan
    f = cue_features(cues, row["yaw_conf"], layout, fit, rmse)
    return [f[n] for n in names]


def load(seeds: tuple[int, ...], families: list[str]) -> dict[str, list[dict]]:
    out = {}
    for fam in families:
        for seed in seeds:
            f = OUT / f"{fam}-{seed}.jsonl"
            if f.is_file():
                out[f"{fam}-{seed}"] = [json.loads(x) for x in f.read_text().splitlines()]
    return out


def table(worlds: dict[str, list[dict]], names: list[str], need: str | None):
    """X, y, world index over the rows that have the field `need` (None: every row)."""
    X, y, w = [], [], []
    one = len(worlds) == 1  # one world: two folds by query
    for k, queries in enumerate(worlds.values()):
        for n, q in enumerate(queries):
            k = n % 2 if one else k
            for row in q["rows"]:
                if need and need not in row:
                    continue
                X.append(features(row, names))
                y.append(row["true"])
                w.append(k)
    return np.array(X, float), np.array(y, float), np.array(w)


def fit_logistic(X: np.ndarray, y: np.ndarray, ridge: float = 1.0):
    """(mean, scale, coefficients with the bias first) by Newton's method."""
    mu, sd = X.mean(axis=0), X.std(axis=0) + 1e-9
    Z = np.hstack([np.ones((len(X), 1)), (X - mu) / sd])
    beta = np.zeros(Z.shape[1])
    for _ in range(50):
        p = 1.0 / (1.0 + np.exp(-np.clip(Z @ beta, -40, 40)))
        g = Z.T @ (p - y) + ridge * np.r_[0.0, beta[1:]]
        H = (Z * (p * (1 - p))[:, None]).T @ Z + ridge * np.diag(np.r_[0.0, np.ones(len(beta) - 1)])
        step = np.linalg.solve(H, g)
        beta -= step
        if np.abs(step).max() < 1e-8:
            break
    return mu, sd, beta


def predict(model, X: np.ndarray) -> np.ndarray:
    mu, sd, beta = model
    z = beta[0] + ((X - mu) / sd) @ beta[1:]
    return 1.0 / (1.0 + np.exp(-np.clip(z, -40, 40)))


def raw_coefficients(model, names: list[str]) -> dict:
    """The fitted model in the features' own units (what confidence.py evaluates)."""
    mu, sd, beta = model
    w = beta[1:] / sd
    return {"bias": float(beta[0] - (w * mu).sum()), "weights": dict(zip(names, map(float, w)))}


def log_loss(p: np.ndarray, y: np.ndarray) -> float:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return float(-(y * np.log(p) + (1 - y) * np.log(1 - p)).mean())


def held_out(X, y, w, cols, ridge: float) -> np.ndarray:
    """Each world's rows predicted by a model fitted on the other worlds."""
    p = np.empty(len(y))
    for k in np.unique(w):
        m = fit_logistic(X[w != k][:, cols], y[w != k], ridge)
        p[w == k] = predict(m, X[w == k][:, cols])
    return p


def reliability(p: np.ndarray, y: np.ndarray, bins=(0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 1.0001)):
    lines = [
        "| predicted | rows | mean predicted | observed true |",
        "| --- | ---: | ---: | ---: |",
    ]
    for a, b in zip(bins[:-1], bins[1:]):
        sel = (p >= a) & (p < b)
        if sel.any():
            lines.append(
                f"| {a:.2f}-{min(b, 1):.2f} | {int(sel.sum())} | {p[sel].mean():.3f} "
                f"| {y[sel].mean():.3f} |"
            )
    return lines


# The selection world kept out of the fit: tests/test_confidence.py checks the shipped
# calibration against its rows (tests/data/confidence_held_back.json.gz).
HELD_BACK = "mulran-8623"
FAMILY_NAMES = ["nclt", "mulran", "oxford"]


def fit(args: argparse.Namespace) -> None:
    worlds = load(SEEDS["selection"], args.families)
    held = worlds.pop(HELD_BACK, None)
    print(f"fitted on the selection worlds {', '.join(worlds)}; held back: {HELD_BACK}")
    for kind, names in CANDIDATES.items():
        X, y, w = table(worlds, names, NEEDS[kind])
        full = list(range(len(names)))
        base = log_loss(held_out(X, y, w, full, args.ridge), y)
        print(f"\n## every {kind} cue: {len(y)} rows, {int(y.sum())} true; held-out log-loss")
        print(f"{base:.4f} with all of them")
        print("| cue left out | held-out log-loss | change |")
        print("| --- | ---: | ---: |")
        for c, name in enumerate(names):
            rest = [j for j in full if j != c]
            ll = log_loss(held_out(X, y, w, rest, args.ridge), y)
            print(f"| {name} | {ll:.4f} | {ll - base:+.4f} |")
    result, plots = {}, {}
    for kind, names in KINDS.items():
        X, y, w = table(worlds, names, NEEDS[kind])
        p_out = held_out(X, y, w, list(range(len(names))), args.ridge)
        print(
            f"\n## shipped {kind} ({', '.join(names)}): held-out log-loss {log_loss(p_out, y):.4f}"
        )
        print("reliability (each world predicted by a fit on the others):")
        print("\n".join(reliability(p_out, y)))
        model = fit_logistic(X, y, args.ridge)
        result[kind] = raw_coefficients(model, names)
        plots[kind] = (p_out, y)
        if held is not None:
            Xh, yh, _ = table({HELD_BACK: held}, names, NEEDS[kind])
            print(f"\nheld-back world {HELD_BACK} ({len(yh)} rows):")
            print("\n".join(reliability(predict(model, Xh), yh)))
    print(json.dumps(result, indent=1))
    if args.plot:
        reliability_plot(plots, ROOT / "docs" / "images" / "confidence-reliability.png")
    if args.write:
        from disco_cli.model import load_model

        result = {
            "model": load_model("default").fingerprint,
            "fitted_on": sorted(worlds),
            "held_back": HELD_BACK,
            "ridge": args.ridge,
            "command": f"benchmarks/calibrate_confidence.py fit --write --ridge {args.ridge:g}",
            **result,
        }
        FIT_FILE.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {FIT_FILE.relative_to(ROOT)}")
        if held is not None:
            export_held_back(held)


def export_held_back(queries: list[dict]) -> None:
    """The held-back world's checked rows (the best 3 of each query) for the test."""
    import gzip

    keep = ("true", "distance", "rerank", "rerank_own", "signature", "lead", "yaw_conf")
    keep += ("peak", "shift_m", "flipped")
    rows = [
        {k: r[k] for k in keep} for q in queries for r in q["rows"][:CHECK_DEPTH] if "peak" in r
    ]
    out = ROOT / "tests" / "data" / "confidence_held_back.json.gz"
    out.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(out, "wt") as f:
        json.dump({"world": HELD_BACK, "rows": rows}, f, separators=(",", ":"))
    print(f"wrote {out.relative_to(ROOT)} ({len(rows)} rows)")


def reliability_plot(plots: dict, out: Path) -> None:
    """Predicted against observed, per kind, on the held-out predictions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    edges = np.linspace(0, 1, 11)
    for kind, (p, y) in plots.items():
        idx = np.clip(np.digitize(p, edges) - 1, 0, 9)
        xs, ys = [], []
        for b in range(10):
            sel = idx == b
            if sel.sum() >= 10:
                xs.append(p[sel].mean())
                ys.append(y[sel].mean())
        ax.plot(xs, ys, "o-", label=f"{kind} ({len(y)} rows)")
    ax.plot([0, 1], [0, 1], "k--", lw=0.8, label="perfect")
    ax.set_xlabel("predicted confidence (bin mean)")
    ax.set_ylabel("observed share of true revisits")
    ax.set_title("Reliability, selection worlds, each held out in turn")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    print(f"wrote {out.relative_to(ROOT)}")


def loops(args: argparse.Namespace) -> None:
    """Every candidate of the default detector on the joined selection sequences, and
    the precision and recall each confidence bar gives."""
    from disco_cli.evaluation.loop_sequences import (
        joined_scans,
        label_rows,
        loop_radius,
        loop_rows,
        precision_at,
    )

    all_rows = {}
    for fam in args.families:
        for seed in SEEDS["selection"]:
            f = OUT / "loops" / f"{fam}-{seed}.jsonl"
            if not f.is_file():
                t0 = time.monotonic()
                rows = loop_rows(
                    FAMILIES[fam], world(seed, fam), OUT / "joined", min_confidence=None
                )
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
                print(f"  {f.name}: {time.monotonic() - t0:.0f} s", file=sys.stderr)
            rows = [json.loads(x) for x in f.read_text().splitlines()]
            # Labelled again from the poses: rows kept from before a change of radius
            # are judged as new ones would be.
            _, xy = joined_scans(FAMILIES[fam], world(seed, fam), OUT / "joined")
            all_rows[f"{fam}-{seed}"] = label_rows(rows, xy, loop_radius(FAMILIES[fam]))
    bars = np.round(np.arange(0.5, 1.0, 0.01), 2)
    print("| bar | " + " | ".join(all_rows) + " |")
    print("| ---: |" + " ---: |" * len(all_rows))
    curves = {k: precision_at(v, bars) for k, v in all_rows.items()}
    for j, bar in enumerate(bars):
        cells = [f"{c[j][1]:.3f} / {c[j][2]:.3f}" for c in curves.values()]
        print(f"| {bar:.2f} | " + " | ".join(cells) + " |")
    pooled = [r for v in all_rows.values() for r in v]
    ok = [b for b, p, _ in precision_at(pooled, bars) if p >= 0.995]
    print(f"\nlowest bar with pooled precision >= 99.5 %: {min(ok) if ok else None}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--families", nargs="+", default=FAMILY_NAMES)
    c.add_argument("--seeds", choices=sorted(SEEDS), default="selection")
    f = sub.add_parser("fit")
    f.add_argument("--families", nargs="+", default=FAMILY_NAMES)
    f.add_argument("--ridge", type=float, default=1.0)
    f.add_argument("--write", action="store_true")
    f.add_argument("--plot", action="store_true", help="docs/images/confidence-reliability.png")
    lp = sub.add_parser("loops")
    lp.add_argument("--families", nargs="+", default=FAMILY_NAMES)
    args = ap.parse_args()
    if args.cmd == "collect":
        for fam in args.families:
            for seed in SEEDS[args.seeds]:
                collect(fam, seed)
    elif args.cmd == "fit":
        fit(args)
    else:
        loops(args)


if __name__ == "__main__":
    main()
