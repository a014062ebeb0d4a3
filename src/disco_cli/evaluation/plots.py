"""PNG plots of an evaluation: Recall@N, precision-recall, yaw-error histogram, rejection.

matplotlib is optional (`pip install 'disco-cli[plot]'`): without it the plots are
skipped with one warning and every metric is still written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.evaluation.metrics import Evaluation
from disco_cli.io.output_paths import write_atomic

INSTALL_HINT = "matplotlib is not installed, so no plots; pip install 'disco-cli[plot]'"


def _pyplot() -> Any | None:
    try:
        # deferred: optional extra (and ~0.7 s): only a report with plots loads it
        import matplotlib

        matplotlib.use("Agg")  # files only, never a window
        import matplotlib.pyplot as plt  # deferred: optional extra, after use("Agg")
    except ImportError:
        return None
    return plt


def write_plots(directory: Path, ev: Evaluation, title: str = "") -> list[Path]:
    """Write the plots that this evaluation has data for; [] (and a warning) without matplotlib."""
    plt = _pyplot()
    if plt is None:
        # deferred: the CLI's console (typer, rich); the library imports without them
        from disco_cli.runtime.console import warn

        warn(INSTALL_HINT)  # warn() prints "[plot]" as it is, not as rich markup
        return []
    directory = Path(directory)
    written = []
    suffix = f" ({title})" if title else ""

    def save(fig: Any, name: str) -> None:
        path = directory / name
        fig.tight_layout()
        try:
            write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=100))
        finally:
            plt.close(fig)
        written.append(path)

    if ev.recall_curve.size:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        n = np.arange(1, ev.recall_curve.size + 1)
        ax.plot(n, 100 * ev.recall_curve, marker="o", markersize=3)
        ax.set(xlabel="N (top-N results)", ylabel="Recall@N [%]", ylim=(0, 101))
        ax.set_title(f"Recall@N{suffix}")
        ax.grid(alpha=0.3)
        save(fig, "recall_at_n.png")

    if ev.pr.thresholds.size and ev.pr.n_positive:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(ev.pr.recall, ev.pr.precision, drawstyle="steps-post")
        ax.set(
            xlabel="Recall",
            ylabel="Precision",
            xlim=(0, 1.01),
            ylim=(0, 1.01),
            title=f"Precision-recall, AUC {ev.pr.auc:.3f}, F1max {ev.pr.f1_max:.3f}{suffix}",
        )
        ax.grid(alpha=0.3)
        save(fig, "precision_recall.png")

    if ev.yaw_errors.size:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        top = max(5.0, float(np.percentile(ev.yaw_errors, 99)))
        ax.hist(np.minimum(ev.yaw_errors, top), bins=40, range=(0, top))
        ax.set(
            xlabel="|yaw error| [deg] (last bin: at or beyond)",
            ylabel="correct top-1 matches",
            title=f"Yaw error, median {np.median(ev.yaw_errors):.2f} deg{suffix}",
        )
        save(fig, "yaw_error.png")

    if ev.rejection is not None and ev.rejection.thresholds.size:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(ev.rejection.recall, ev.rejection.rejection)
        ax.set(
            xlabel="Recall of revisited places (top-1 right and accepted)",
            ylabel="Unseen places rejected",
            xlim=(0, 1.01),
            ylim=(0, 1.01),
            title=f"Unseen-place rejection{suffix}",
        )
        ax.grid(alpha=0.3)
        save(fig, "rejection.png")
    return written
