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
    if rerank > 0 and not hasattr(model, "rerank"):
        from disco_cli.errors import DiscoError

        raise DiscoError(f"model {getattr(model, 'name', '?')} cannot re-rank; use --rerank 0")
    model.rerank_candidates = rerank  # type: ignore[attr-defined]


# Pose files: one vocabulary for every command that reads poses (docs/formats.md, "Pose files").
PANEL_POSES = "Poses"
PosesFormatOpt = Annotated[
    Optional[str],
    typer.Option(
        "--poses-format",
        help="kitti, tum, nclt, mulran, oxford or kitti360; default: from the file's name "
        "and content.",
        rich_help_panel=PANEL_POSES,
    ),
]
CalibOpt = Annotated[
    Optional[str],
    typer.Option(
        "--calib",
        help="KITTI calib.txt (or KITTI-360 calibration/ folder) taking the poses to the "
        "LiDAR; default: calib.txt beside poses.txt when it exists; 'none' keeps the poses "
        "as stored.",
        rich_help_panel=PANEL_POSES,
    ),
]
ExtrinsicOpt = Annotated[
    Optional[Path],
    typer.Option(
        "--extrinsic",
        help="A 4 x 4 text file: the LiDAR's pose in the pose file's frame, applied after "
        "the calibration.",
        rich_help_panel=PANEL_POSES,
    ),
]
MaxTimeGapOpt = Annotated[
    Optional[float],
    typer.Option(
        "--max-time-gap",
        min=0.0,
        help="Seconds: a scan farther than this from the poses around it gets no pose; "
        "default: 3 median periods of the pose file.",
        rich_help_panel=PANEL_POSES,
    ),
]


def pose_options(
    poses_format: str | None, calib: str | None, extrinsic: Path | None, max_time_gap: float | None
) -> dict:
    """The keyword arguments of `disco_cli.poses.ScanPoser` from the four options above."""
    from disco_cli.poses.scans import calib_arg

    return {
        "poses_format": poses_format,
        "calib": calib_arg(calib),
        "extrinsic": extrinsic,
        "max_time_gap": max_time_gap,
    }


ProtocolOpt = Annotated[
    Optional[str],
    typer.Option(
        "--protocol",
        help="The DiSCO paper's protocol on a dataset folder: nclt, mulran or oxford "
        "(docs/datasets.md).",
        rich_help_panel="Protocol",
    ),
]

OxfordScaleOpt = Annotated[
    Optional[float],
    typer.Option(
        "--oxford-scale",
        min=0.001,
        help="Metres per unit of PointNetVLAD's normalized Oxford submaps, with --protocol "
        "oxford; default 20 (docs/datasets.md).",
        rich_help_panel="Protocol",
    ),
]
