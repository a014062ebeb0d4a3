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
TopicOpt = Annotated[
    Optional[str],
    typer.Option(
        "--topic",
        help="ROS bags: the sensor_msgs/PointCloud2 topic to read; default: the bag's only one.",
        rich_help_panel=PANEL_RUN,
    ),
]
PoseTopicOpt = Annotated[
    Optional[str],
    typer.Option(
        "--pose-topic",
        help="ROS bags: the scans' poses from this nav_msgs/Odometry or "
        "geometry_msgs/PoseStamped topic of the bag, interpolated at each scan's stamp.",
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
    if rerank > 0 and not hasattr(model, "rerank"):
        from disco_cli.errors import DiscoError

        raise DiscoError(f"model {getattr(model, 'name', '?')} cannot re-rank; use --rerank 0")
    model.rerank_candidates = rerank  # type: ignore[attr-defined]
