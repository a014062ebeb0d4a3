"""`disco eval`: place-recognition metrics against ground-truth poses (multi-session).

The paper's protocol: scans of one session are queried against a database of another;
the database's stored poses are the ground truth. The work is
`evaluation.runs.multi_session`; `disco eval-loops` (eval_loops.py) shares the
options and the report below. Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from disco_cli.commands.options import (
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    OxfordScaleOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    ProtocolOpt,
    RerankOpt,
    ScanFormatOpt,
    TopicOpt,
    apply_rerank,
    db_option,
    model_option,
    opt,
    pose_options,
    topk_option,
)
from disco_cli.console import OutputFormat, handle_errors

PANEL_INPUT = "Input"
PANEL_PROTOCOL = "Protocol"
PANEL_OUTPUT = "Output"


@contextmanager
def _bar(total: int) -> Iterator[Callable[[int], None]]:
    """A progress bar for embedding `total` scans; yields its step function."""
    from disco_cli.console import progress

    with progress(transient=True) as bar:
        task = bar.add_task("embedding", total=total, rate="")
        yield lambda k: bar.advance(task, k)


def _run_protocol(
    name: str,
    inputs: list[Path],
    model_name: str | None,
    device: str,
    rerank: Any,
    fmt: Any,
    oxford_scale: float | None = None,
) -> None:
    """`eval --protocol NAME ROOT`: the paper's sessions and thresholds (disco_cli.protocols),
    printed in the layout of its table."""
    from disco_cli.console import RowWriter, stderr, warn
    from disco_cli.errors import DiscoError
    from disco_cli.model import load_model
    from disco_cli.protocols import TABLE_COLUMNS, run_protocol, table_rows

    if len(inputs) != 1:
        raise DiscoError("--protocol takes one dataset folder")
    model = load_model(model_name or "default", device=device)
    apply_rerank(model, rerank)
    say = lambda msg: stderr.print(msg, highlight=False)  # noqa: E731
    proto, results = run_protocol(
        name, inputs[0], model, warn=warn, progress=say, oxford_scale=oxford_scale
    )
    rows = table_rows(proto, results, approach=f"disco ({model.name})")
    RowWriter(TABLE_COLUMNS, fmt, digits=2).write(rows, title=f"{proto.dataset}: {model.name}")


def _report_and_print(
    ev: Any, run: dict[str, Any], report: Path | None, fmt: OutputFormat | None
) -> None:
    from disco_cli.console import stderr
    from disco_cli.evaluation.report import print_metrics, write_report

    if report is not None:
        written = write_report(report, ev, run)
        stderr.print(f"wrote {len(written)} files to {report}", highlight=False)
    print_metrics(ev.metrics, fmt, title=f"{run.get('protocol')}: {run.get('model')}")


# Options shared by both commands.
RadiusOpt = Annotated[
    float,
    opt("--radius", min=0.0, help="True match within this many metres.", panel=PANEL_PROTOCOL),
]
ReportOpt = Annotated[
    Optional[Path],
    opt(
        "--report",
        panel=PANEL_OUTPUT,
        help="Write metrics.json, curves.json, summary.md and PNG plots into this folder.",
    ),
]
FormatOpt = Annotated[
    Optional[OutputFormat],
    opt(
        "--format",
        panel=PANEL_OUTPUT,
        help="table (default on a terminal), tsv (default in a pipe) or jsonl (one object).",
    ),
]


@handle_errors
def evaluate(
    queries: Annotated[
        list[Path],
        typer.Argument(
            help="Query scans: files or folders (velodyne/ layout); with --protocol, the "
            "dataset folder.",
            show_default=False,
        ),
    ],
    db_path: Annotated[
        Optional[Path], db_option("Map database of another session, with poses.", panel=PANEL_INPUT)
    ] = None,
    protocol: ProtocolOpt = None,
    oxford_scale: OxfordScaleOpt = None,
    query_poses: Annotated[
        Optional[Path],
        opt(
            "--query-poses",
            panel=PANEL_INPUT,
            help="Poses of the queries; default: the pose file in a single query folder.",
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    model_name: Annotated[
        Optional[str],
        model_option(
            "Model name or checkpoint; default: the one that built the database.",
            panel=PANEL_PROTOCOL,
        ),
    ] = None,
    radius: RadiusOpt = 3.0,
    topk: Annotated[int, topk_option("Recall@1..N up to this N.", panel=PANEL_PROTOCOL)] = 25,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    report: ReportOpt = None,
    fmt: FormatOpt = None,
) -> None:
    """Multi-session evaluation: Recall@N, Recall@1%, PR AUC, F1max, yaw error vs a database."""
    from disco_cli.console import warn
    from disco_cli.errors import PoseFileError
    from disco_cli.evaluation.runs import multi_session, posed_scans
    from disco_cli.map import Map
    from disco_cli.pipeline import file_beside, scan_paths
    from disco_cli.search import rerank_depth

    if protocol is not None:
        return _run_protocol(protocol, queries, model_name, device, rerank, fmt, oxford_scale)
    if db_path is None:
        raise PoseFileError("give --db map.db (or --protocol NAME DATASET_FOLDER)")
    paths = scan_paths(queries, scan_format, topic)
    poses_file = file_beside(queries, query_poses)
    if poses_file is None and pose_topic is None:
        raise PoseFileError("no query poses: give --query-poses FILE (or a folder with poses.txt)")
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, q_poses = posed_scans(paths, poses_file, opts, warn, pose_topic)
    with Map.open(db_path, model=model_name, device=device) as m, _bar(len(paths)) as step:
        apply_rerank(m.model, rerank)
        ev = multi_session(paths, q_poses, m.database, m.model, radius, topk, scan_format, step)
    run = {
        "protocol": "multi-session",
        "model": m.model.name,
        "fingerprint": m.model.fingerprint,
        "rerank": rerank_depth(m.model),
        "database": str(db_path),
        "queries": " ".join(map(str, queries)),
        "query_poses": str(poses_file) if pose_topic is None else pose_topic,
        "radius_m": radius,
        "topk": topk,
    }
    _report_and_print(ev, run, report, fmt)
