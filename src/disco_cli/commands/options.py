"""Options that several commands share, declared once so that they read the same everywhere."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.console import OutputFormat
from disco_cli.readers import FormatName

PANEL_RUN = "Running"
PANEL_OUT = "Output"

OutputFormatOpt = Annotated[
    Optional[OutputFormat],
    typer.Option(
        "--format",
        help="table, tsv or jsonl; default: a table on a terminal, TSV in a pipe.",
        rich_help_panel=PANEL_OUT,
    ),
]

ScanFormatOpt = Annotated[
    Optional[FormatName],
    typer.Option(
        "--scan-format",
        help="Scan format; default: from the extension and folder.",
        rich_help_panel=PANEL_RUN,
    ),
]
WorkersOpt = Annotated[
    int,
    typer.Option(
        "--workers",
        min=1,
        max=64,
        help="Threads reading and voxelizing scans.",
        rich_help_panel=PANEL_RUN,
    ),
]
DeviceOpt = Annotated[
    str, typer.Option("--device", help="cpu or cuda (for the network).", rich_help_panel=PANEL_RUN)
]
RerankOpt = Annotated[
    Optional[int],
    typer.Option(
        "--rerank",
        min=0,
        help="Re-rank this many nearest signatures (0: signature order only, as in the "
        "paper); default: the model's own (10 for DiSCO and Scan Context).",
        rich_help_panel=PANEL_RUN,
    ),
]


def apply_rerank(model: object, rerank: int | None) -> None:
    """Set the model's re-ranking depth when --rerank was given."""
    if rerank is None:
        return
    from disco_cli.search import check_rerank

    model.rerank_candidates = check_rerank(model, rerank)  # type: ignore[attr-defined]


def opt(*flags: str, help: str, panel: str | None = None, **kw: object) -> typer.models.OptionInfo:
    """A typer.Option declared in one line: flags, help text, help panel."""
    return typer.Option(*flags, help=help, rich_help_panel=panel, **kw)  # type: ignore[arg-type]


BatchOpt = Annotated[
    int, opt("--batch", help="Scans per network batch.", panel=PANEL_RUN, min=1, max=4096)
]
CalibOpt = Annotated[
    Optional[Path], opt("--calib", help="KITTI calib.txt: camera poses -> LiDAR poses.")
]
ModelOpt = Annotated[
    str,
    opt("--model", "-m", help="default, spectral, scancontext or a checkpoint path.",
        panel=PANEL_RUN),
]  # fmt: skip
TimesOpt = Annotated[
    Optional[Path],
    opt("--times", help="Timestamps (s), one per scan; default: times.txt beside the scans.",
        panel=PANEL_RUN),
]  # fmt: skip
ExcludeFramesOpt = Annotated[
    Optional[int],
    opt("--exclude-frames", min=1,
        help="Search only scans at least this many frames before the query."),
]  # fmt: skip
ExcludeSecondsOpt = Annotated[
    Optional[float],
    opt("--exclude-seconds", min=0.0,
        help="Search only scans at least this many seconds before the query (needs times)."),
]  # fmt: skip
