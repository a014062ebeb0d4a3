"""Evaluation reports: metrics.json, curves.json, a Markdown summary and the terminal output.

`metrics.json` holds the figures (fractions in [0, 1], yaw errors in degrees, counts,
and under "run" what was evaluated and how); `curves.json` the curves behind them
(precision-recall, recall@N, unseen-place rejection, the yaw errors); `summary.md` the
same figures as a table a person reads. PNG plots come from `plots.py`.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.evaluation.metrics import Evaluation
from disco_cli.evaluation.plots import write_plots
from disco_cli.io.output_paths import check_output_folder, write_text_atomic
from disco_cli.query.search import effective_policy

# The figures shown on the terminal and in the summary, in this order, with their labels.
FIGURES = [
    ("recall@1", "Recall@1"),
    ("recall@1%", "Recall@1%"),
    ("auc", "PR AUC"),
    ("f1_max", "F1max"),
    ("recall@100%precision", "Recall @ 100% precision"),
    ("yaw_err_mean_deg", "Yaw error mean (deg)"),
    ("yaw_err_std_deg", "Yaw error std (deg)"),
    ("yaw_err_median_deg", "Yaw error median (deg)"),
    ("num_queries", "Queries"),
    ("num_queries_with_match", "Queries with a true match"),
    ("num_database", "Database scans"),
    ("num_correct_top1", "Correct top-1"),
]


def _finite(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, dtype=np.float64)]


def curves_dict(ev: Evaluation) -> dict[str, Any]:
    out: dict[str, Any] = {
        "pr": {
            "threshold": _finite(ev.pr.thresholds),
            "precision": _finite(ev.pr.precision),
            "recall": _finite(ev.pr.recall),
        },
        "recall_at_n": _finite(ev.recall_curve),
        "yaw_errors_deg": _finite(ev.yaw_errors),
    }
    if ev.rejection is not None:
        out["rejection"] = {
            "threshold": _finite(ev.rejection.thresholds),
            "rejection": _finite(ev.rejection.rejection),
            "recall": _finite(ev.rejection.recall),
        }
    return out


def format_value(key: str, value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, int):
        return str(value)
    if key.endswith("_deg"):
        return f"{value:.2f}"
    return f"{100.0 * value:.2f} %"


def rows(metrics: dict[str, Any]) -> list[tuple[str, str, Any]]:
    """(key, label, value) for each figure the run has."""
    return [(key, label, metrics[key]) for key, label in FIGURES if key in metrics]


def markdown_summary(metrics: dict[str, Any], run: dict[str, Any], plots: list[str]) -> str:
    lines = [f"# disco evaluation: {metrics.get('protocol', '')}", ""]
    for key, value in run.items():
        lines.append(f"- {key}: `{value}`")
    lines += ["", "| figure | value |", "| --- | ---: |"]
    lines += [f"| {label} | {format_value(key, value)} |" for key, label, value in rows(metrics)]
    recalls = metrics.get("recall@N") or []
    if recalls:
        shown = [1, 5, 10, 25]
        cells = [f"@{n}: {format_value('r', recalls[n - 1])}" for n in shown if n <= len(recalls)]
        lines += ["", "Recall@N: " + ", ".join(cells)]
    if plots:
        lines += [""] + [f"![{Path(p).stem}]({Path(p).name})" for p in plots]
    return "\n".join(lines) + "\n"


def write_report(directory: Path, ev: Evaluation, run: dict[str, Any]) -> list[Path]:
    """Write metrics.json, curves.json, summary.md and the plots into `directory` (made
    if it is missing; its parent must exist), each file atomically."""
    directory = check_output_folder(directory, what="the report")
    try:
        directory.mkdir(exist_ok=True)
    except OSError as exc:
        raise DiscoError(f"{directory}: cannot make the folder ({exc.strerror or exc})") from None
    metrics = dict(ev.metrics)
    metrics["run"] = run
    written = [directory / "metrics.json", directory / "curves.json"]
    write_text_atomic(written[0], json.dumps(metrics, indent=2) + "\n")
    write_text_atomic(written[1], json.dumps(curves_dict(ev)) + "\n")
    pngs = write_plots(directory, ev, title=str(run.get("model", "")))
    summary = directory / "summary.md"
    write_text_atomic(summary, markdown_summary(ev.metrics, run, [str(p) for p in pngs]))
    return written + [summary] + pngs


def print_metrics(metrics: dict[str, Any], fmt: Any, title: str) -> None:
    """The figures on stdout: a rich table, `metric<TAB>value` lines, or one JSON object."""
    # deferred: the CLI's console (typer, rich); the library imports without them
    from disco_cli.runtime.console import OutputFormat, resolve_format

    fmt = resolve_format(fmt)
    if fmt is OutputFormat.jsonl:
        sys.stdout.write(json.dumps(metrics) + "\n")
    elif fmt is OutputFormat.tsv:
        out = ["metric\tvalue"]
        out += [f"{key}\t{'' if v is None else v}" for key, _, v in rows(metrics)]
        sys.stdout.write("\n".join(out) + "\n")
    else:
        from rich.console import Console  # deferred: rich, as above
        from rich.table import Table

        table = Table(title=title, title_justify="left")
        table.add_column("figure")
        table.add_column("value", justify="right")
        for key, label, value in rows(metrics):
            table.add_row(label, format_value(key, value))
        Console(highlight=False).print(table)
    sys.stdout.flush()


def model_run(model: Any, policy: Any = None) -> dict[str, Any]:
    """What a report's "run" says about the model and the query stage: its name,
    fingerprint, re-ranking (the wider pass, the signature's weight in the score), the
    snap, how many matches per query got the parallax-free yaw, and the whole
    `QueryPolicy` it ran under (`policy`, None: the model's; less what the model cannot
    do)."""
    p = effective_policy(model, policy)
    depth = p.rerank_candidates
    run = {"model": model.name, "fingerprint": model.fingerprint, "rerank": depth}
    if p.wider:
        run["rerank_wider"] = {"depth": p.wider, "above": p.rerank_wider_above}
    if depth and p.signature_weight:
        run["rerank_signature_weight"] = p.signature_weight
    if p.snaps:
        run["snap"] = {"radius_m": p.snap_radius, "margin": p.snap_margin}
    run["refine_yaw"] = p.refine_yaw
    run["policy"] = p.report()
    return run


def report_and_print(ev: Evaluation, run: dict[str, Any], directory: Path | None, fmt: Any) -> None:
    """`disco eval`'s ending: the report files into `directory` when given (said on
    stderr), then the figures on stdout (`print_metrics`)."""
    from disco_cli.runtime.console import stderr  # deferred: as in print_metrics

    if directory is not None:
        written = write_report(directory, ev, run)
        stderr.print(f"wrote {len(written)} files to {directory}", highlight=False)
    print_metrics(ev.metrics, fmt, title=f"{run.get('protocol')}: {run.get('model')}")
