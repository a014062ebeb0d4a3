"""Options that several commands share, declared once so that they read the same everywhere.

The vocabulary (tests/test_cli_options.py walks every command and holds it):

- `--format`: the OUTPUT format of result rows (table, tsv, jsonl); nothing else.
- `--scan-format`: the INPUT scan format (kitti, nclt, npy, pcd, ply).
- `-m` is `--model`, `-d` is `--db`, `-k` is `--topk`, `-o` is `--output`: a short
  flag means one thing in every command.
- `--calib FILE|none`: a KITTI calib.txt; `none` switches off the one beside poses.txt.

Flags that every command spells the same but whose help differs per command are
factories (`model_option(help)`) used as `Annotated[str, model_option("...")]`.
At the end, the longer declarations of single commands (`query`'s filters, the
relative-pose flags of `query` and `loops`, `eval`'s report), so that each command
module reads as its flow: parse, read the inputs, call the library, write rows.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from disco_cli.io.readers import FormatName
from disco_cli.runtime.console import OutputFormat, set_quiet

PANEL_RUN = "Running"
PANEL_OUT = "Output"
PANEL_IN = "Input"
PANEL_POSE = "Relative pose"
PANEL_PROTOCOL = "Protocol"
# --model's help: a model to load, or (commands that open a map) the map's own by default.
MODEL_NAMES = "default, spectral, scancontext or a checkpoint path."
MODEL_OF_MAP = (
    "Model name or checkpoint path; default: the one that built the database (needed "
    "for checkpoint paths)."
)

OutputFormatOpt = Annotated[
    Optional[OutputFormat],
    typer.Option(
        "--format",
        help="table, tsv or jsonl; default: a table on a terminal, TSV in a pipe.",
        rich_help_panel=PANEL_OUT,
    ),
]


def model_option(help: str, panel: str | None = PANEL_RUN) -> Any:
    """`--model/-m NAME|PATH`."""
    return typer.Option("--model", "-m", help=help, rich_help_panel=panel)


def db_option(help: str, panel: str | None = None) -> Any:
    """`--db/-d FILE`: a map database."""
    return typer.Option("--db", "-d", help=help, rich_help_panel=panel)


def topk_option(help: str, panel: str | None = None) -> Any:
    """`--topk/-k N`: one range in every command."""
    return typer.Option("--topk", "-k", min=1, max=10000, help=help, rich_help_panel=panel)


def output_option(help: str, panel: str | None = None) -> Any:
    """`--output/-o FILE`: a file the command writes (its type from the suffix)."""
    return typer.Option("--output", "-o", help=help, rich_help_panel=panel)


def calib_option(help: str, panel: str | None = None) -> Any:
    """`--calib FILE|none`."""
    return typer.Option("--calib", metavar="FILE|none", help=help, rich_help_panel=panel)


def calib_file(given: Path | None, poses_file: Path | None) -> Path | None:
    """The calib.txt to apply: `--calib FILE`, none for `--calib none`, else the
    calib.txt beside the poses file when there is one."""
    if given is not None:
        return None if str(given).lower() == "none" else given
    if poses_file is not None:
        beside = Path(poses_file).parent / "calib.txt"
        if beside.is_file():
            return beside
    return None


ScanFormatOpt = Annotated[
    Optional[FormatName],
    typer.Option(
        "--scan-format",
        help="Scan format; default: from the extension and folder.",
        rich_help_panel=PANEL_RUN,
    ),
]
ScanRootOpt = Annotated[
    Optional[Path],
    typer.Option(
        "--scan-root",
        file_okay=False,
        help="Where the database's scans are now, when neither their stored absolute "
        "path nor their path relative to the database finds them (a map mounted elsewhere).",
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
        rich_help_panel="Poses",
    ),
]
# `--threads N` on every command that computes (disco_cli/runtime/threads.py applies it).
ThreadsOpt = Annotated[
    Optional[int],
    typer.Option(
        "--threads",
        min=1,
        max=256,
        show_default=False,
        help="CPU threads: scans read and voxelized in parallel, and torch, search and "
        "voxelizer threads; default: $DISCO_THREADS, else 1 (holds its speed beside "
        "other busy processes).",
        rich_help_panel=PANEL_RUN,
    ),
]
# Long commands: a progress bar on a terminal, a line every few seconds in a log.
QuietOpt = Annotated[
    bool,
    typer.Option(
        "--quiet",
        "-q",
        callback=set_quiet,
        help="No progress and no summary lines (wrote N scans, ...): only results, "
        "warnings and errors print.",
        rich_help_panel=PANEL_OUT,
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
        "paper); default: the model's own (10 for DiSCO and Scan Context). DiSCO re-ranks "
        "down to 40 when none of them matches well (distance above 0.7).",
        rich_help_panel=PANEL_RUN,
    ),
]


RerankWiderOpt = Annotated[
    Optional[int],
    typer.Option(
        "--rerank-wider",
        min=0,
        help="Where none of the re-ranked candidates matches well (distance above 0.7), "
        "re-rank down to this many nearest signatures (0: never); default: the model's own "
        "(40 for DiSCO).",
        rich_help_panel=PANEL_RUN,
    ),
]


SnapRadiusOpt = Annotated[
    Optional[float],
    typer.Option(
        "--snap-radius",
        min=0.0,
        metavar="M",
        help="Where the map has poses, make the best match the map scan nearest the "
        "query's position estimated from it, among those within M m of it that re-rank "
        "about as well (0: the best re-ranked); default: the model's own (5 for DiSCO).",
        rich_help_panel=PANEL_RUN,
    ),
]


IndexOpt = Annotated[
    str,
    typer.Option(
        "--index",
        metavar="auto|exact|ann",
        help="The signature search: exact, ann (approximate, for maps of millions of scans; "
        "kept beside the map as MAP.ann and rebuilt when the map changed; needs "
        "pip install 'disco-cli\\[ann]') or auto (ann from 200,000 scans when installed).",
        rich_help_panel=PANEL_RUN,
    ),
]


RefineYawOpt = Annotated[
    Optional[int],
    typer.Option(
        "--refine-yaw",
        min=0,
        help="Give this many best matches per query the parallax-free yaw (the query "
        "re-centred on the match, about 1.5 ms each; 0: plain phase correlation). "
        "Default 1.",
        rich_help_panel=PANEL_RUN,
    ),
]


RepairOpt = Annotated[
    bool,
    typer.Option(
        "--repair",
        help="Re-embed the map's damaged scans (disco info --check lists them) from these "
        "inputs, with their poses and times, and rewrite their rows.",
        rich_help_panel=PANEL_IN,
    ),
]
AppendOpt = Annotated[
    bool,
    typer.Option(
        "--append",
        help="Add these scans to an existing database built from other scans (same model).",
        rich_help_panel=PANEL_IN,
    ),
]
CopyFromOpt = Annotated[
    Optional[str],
    typer.Option(
        "--from",
        help="Copy the map MAP (a file, milvus:PATH or milvus://HOST:PORT/NAME) into a new "
        "--output without embedding again; no scans are given (docs/scaling.md).",
        metavar="MAP",
        rich_help_panel=PANEL_IN,
    ),
]
SkipBadOpt = Annotated[
    bool,
    typer.Option(
        "--skip-bad",
        help="Warn about unreadable scans and go on, instead of stopping at the first.",
        rich_help_panel=PANEL_RUN,
    ),
]
SideViewsOpt = Annotated[
    Optional[float],
    typer.Option(
        "--side-views",
        metavar="METRES",
        min=0.0,
        max=20.0,
        help="Side views: each scan also seen from METRES to its left and right, for "
        "revisits that drive beside the first pass (about 3x the embedding time; a map "
        "keeps its own setting when adding; default: none).",
        rich_help_panel=PANEL_RUN,
    ),
]


def opt(*flags: str, help: str, panel: str | None = None, **kw: Any) -> Any:
    """A typer.Option declared in one call: flags, help text, help panel."""
    return typer.Option(*flags, help=help, rich_help_panel=panel, **kw)


def batch_option(help: str = "Scans per network batch.") -> Any:
    """`--batch N`."""
    return opt("--batch", help=help, panel=PANEL_RUN, min=1, max=4096)


def times_option(panel: str | None = PANEL_RUN) -> Any:
    """`--times FILE`."""
    return opt(
        "--times",
        help="Timestamps (s), one per scan; default: times.txt beside the scans.",
        panel=panel,
    )


POSES_HELP = (
    "Poses of the scans given (KITTI by frame, or by time: --poses-format); default: the "
    "pose file beside the scans."
)


def poses_option(panel: str | None = None, help: str = POSES_HELP) -> Any:
    """`--poses FILE`: the poses of the scans given on the command line, in every command
    (a map's own poses are in the map)."""
    return opt("--poses", panel=panel, help=help)


BatchOpt = Annotated[int, batch_option()]
TimesOpt = Annotated[Optional[Path], times_option()]
ExcludeFramesOpt = Annotated[
    Optional[int],
    opt(
        "--exclude-frames",
        min=1,
        help="Search only scans at least this many frames before the query.",
    ),
]
ExcludeSecondsOpt = Annotated[
    Optional[float],
    opt(
        "--exclude-seconds",
        min=0.0,
        help="Search only scans at least this many seconds before the query (needs times).",
    ),
]


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
    """The keyword arguments of `disco_cli.io.poses.ScanPoser` from the four options above."""
    # deferred: the pose readers load numpy (~0.1 s); every command imports this module
    from disco_cli.io.poses.scans import calib_arg

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
        rich_help_panel=PANEL_PROTOCOL,
    ),
]

OxfordScaleOpt = Annotated[
    Optional[float],
    typer.Option(
        "--oxford-scale",
        min=0.001,
        help="Metres per unit of PointNetVLAD's normalized Oxford submaps, with --protocol "
        "oxford; default 20 (docs/datasets.md).",
        rich_help_panel=PANEL_PROTOCOL,
    ),
]


# `disco eval` and `disco eval-loops`.
RadiusOpt = Annotated[
    float,
    opt("--radius", min=0.0, help="True match within this many metres.", panel=PANEL_PROTOCOL),
]
ReportOpt = Annotated[
    Optional[Path],
    opt(
        "--report",
        panel=PANEL_OUT,
        help="Write metrics.json, curves.json, summary.md and PNG plots into this folder.",
    ),
]
MetricsFormatOpt = Annotated[
    Optional[OutputFormat],
    opt(
        "--format",
        panel=PANEL_OUT,
        help="table (default on a terminal), tsv (default in a pipe) or jsonl (one object).",
    ),
]


# `disco query`: filters on the matches, and their relative pose.
PANEL_FILTER = "Filters"
ExcludeRadiusOpt = Annotated[
    Optional[float],
    opt(
        "--exclude-radius",
        min=0.0,
        panel=PANEL_FILTER,
        help="Drop matches whose stored "
        "pose is within this many metres (x, y) of the query's pose (needs --poses).",
    ),
]
# The distance cut of `query` and `loops` (`loops --threshold` before; usage.DEPRECATED).
MaxDistanceOpt = Annotated[
    Optional[float],
    opt(
        "--max-distance",
        min=0.0,
        panel=PANEL_FILTER,
        help="Keep only matches with a distance at most this (the `distance` column); "
        "default: all.",
    ),
]
PoseOpt = Annotated[
    bool,
    opt(
        "--pose",
        panel=PANEL_POSE,
        help="Also estimate the full relative pose of each match "
        "(phase correlation + ICP on the points): yaw_deg becomes the refined yaw, and "
        "roll_deg, pitch_deg, dx, dy, dz, fitness, accepted are added (JSON lines also carry "
        "the 4 x 4 T).",
    ),
]
VerifyMatchesOpt = Annotated[
    bool,
    opt(
        "--verify",
        panel=PANEL_POSE,
        help="Keep only matches whose relative pose is accepted (implies --pose).",
    ),
]

# `disco loops`: which pairs are loops, and their relative pose.
VerifyLoopsOpt = Annotated[
    bool,
    opt(
        "--verify",
        panel=PANEL_POSE,
        help="Estimate each pair's relative pose (phase "
        "correlation + ICP) and keep only the accepted ones: yaw_deg becomes the refined "
        "yaw, roll_deg and pitch_deg are added (JSON lines also carry the 4 x 4 T).",
    ),
]
VerboseLoopsOpt = Annotated[
    bool,
    opt(
        "--verbose",
        "-v",
        panel=PANEL_POSE,
        help="Estimate each pair's relative pose and "
        "show it (dx, dy, dz, fitness, rmse, accepted, reason), rejected pairs included "
        "unless --verify.",
    ),
]
LoopFileOpt = Annotated[
    Optional[Path],
    output_option(
        "Also write the loops with their relative poses: .g2o (EDGE_SE3:QUAT, "
        "accepted loops only), .tum or .csv.",
        panel=PANEL_OUT,
    ),
]
ReuseDbOpt = Annotated[
    Optional[Path],
    db_option(
        "Reuse the signatures of a database built from this sequence (same model); "
        "scans not in it are embedded.",
        panel=PANEL_RUN,
    ),
]


# One confidence per answer (query/confidence.py): the estimated probability that a row
# is a true revisit, and the geometric check of the best few candidates behind it.
def min_confidence_option(help: str) -> Any:
    """`--min-confidence P` (a probability)."""
    return opt("--min-confidence", min=0.0, max=1.0, panel=PANEL_FILTER, help=help)


MinConfidenceOpt = Annotated[
    Optional[float],
    min_confidence_option(
        "Keep only matches whose confidence (the estimated probability of a true revisit) "
        "is at least this; default: all."
    ),
]
NoCheckOpt = Annotated[
    bool,
    opt(
        "--no-check",
        panel=PANEL_RUN,
        help="Skip the geometric check of the best 3 candidates (their height images "
        "phase-correlated with the query's, a few ms each): faster, rows in "
        "place-recognition order, confidence from place recognition alone.",
    ),
]
# `disco loops`: the loops it reports. The default of --min-confidence is
# query/loop_detector.LOOP_MIN_CONFIDENCE (a test keeps the two equal; the command line
# does not load the detector for --help).
DEFAULT_MIN_CONFIDENCE = 0.85
LoopMinConfidenceOpt = Annotated[
    Optional[float],
    min_confidence_option(
        "Report only loops whose confidence (the estimated probability that the loop is "
        f"true) is at least this; default {DEFAULT_MIN_CONFIDENCE}, chosen on the selection "
        "worlds: no false loop on any of them, precision 99.5 % or more asked "
        "(docs/confidence.md)."
    ),
]
AllLoopsOpt = Annotated[
    bool,
    opt(
        "--all",
        panel=PANEL_FILTER,
        help="Report every candidate, whatever its confidence (each scan's best --topk).",
    ),
]
SequenceArg = Annotated[
    Path,
    typer.Argument(
        show_default=False,
        help="The sequence: a folder of scans (KITTI-style DIR/velodyne/ or a folder of scan "
        "files), or a ROS bag.",
    ),
]
