"""Options that several commands share, declared once so that they read the same everywhere."""

from __future__ import annotations

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
