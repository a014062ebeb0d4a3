"""`disco eval`: place-recognition metrics against ground-truth poses (multi-session).

The paper's protocol: scans of one session are queried against a database of another;
the database's stored poses are the ground truth. The work is
`evaluation.runs.multi_session`, or with --protocol `protocols.run_protocol`; the
report is `evaluation.report`. Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import (
    MODEL_OF_MAP,
    PANEL_IN,
    PANEL_PROTOCOL,
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    MetricsFormatOpt,
    OxfordScaleOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    ProtocolOpt,
    QuietOpt,
    RadiusOpt,
    RefineYawOpt,
    ReportOpt,
    RerankOpt,
    RerankWiderOpt,
    ScanFormatOpt,
    SnapRadiusOpt,
    ThreadsOpt,
    TopicOpt,
    db_option,
    model_option,
    pose_options,
    poses_option,
    topk_option,
)
from disco_cli.errors import DiscoError, PoseFileError
from disco_cli.query.query_policy import policy_for
from disco_cli.runtime.console import RowWriter, handle_errors, stderr, steps, warn


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
        Optional[Path], db_option("Map database of another session, with poses.", panel=PANEL_IN)
    ] = None,
    protocol: ProtocolOpt = None,
    oxford_scale: OxfordScaleOpt = None,
    query_poses: Annotated[
        Optional[Path],
        poses_option(
            PANEL_IN,
            help="Poses of the query scans; default: the pose file in a single query folder "
            "(the map's are in the map).",
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    model_name: Annotated[Optional[str], model_option(MODEL_OF_MAP, panel=PANEL_PROTOCOL)] = None,
    radius: RadiusOpt = 3.0,
    topk: Annotated[int, topk_option("Recall@1..N up to this N.", panel=PANEL_PROTOCOL)] = 25,
    device: DeviceOpt = "cpu",
    threads: ThreadsOpt = None,
    rerank: RerankOpt = None,
    rerank_wider: RerankWiderOpt = None,
    refine_yaw: RefineYawOpt = None,
    snap_radius: SnapRadiusOpt = None,
    report: ReportOpt = None,
    fmt: MetricsFormatOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Multi-session evaluation: Recall@N, Recall@1%, PR AUC, F1max, yaw error vs a database."""
    # deferred: loaded when the command runs, not at start-up (--help imports every command)
    from disco_cli.runtime.threads import set_threads

    set_threads(threads)  # first: torch and BLAS read it as they load
    # deferred: numpy and the evaluation code (~0.2 s) load when it runs, not for --help
    from disco_cli.evaluation.protocols import TABLE_COLUMNS, run_protocol, table_rows
    from disco_cli.evaluation.report import model_run, report_and_print
    from disco_cli.evaluation.runs import multi_session, posed_scans
    from disco_cli.io.missed_poses import no_poses_error
    from disco_cli.io.output_paths import check_output_folder
    from disco_cli.io.scan_inputs import file_beside, scan_paths
    from disco_cli.maps.facade import Map
    from disco_cli.model import load_model

    check_output_folder(report, what="the report")  # before the work it would lose
    settings = dict(rerank=rerank, rerank_wider=rerank_wider, snap_radius=snap_radius)
    settings["refine_yaw"] = refine_yaw  # the query stage's (QueryPolicy)
    if protocol is not None:  # the paper's sessions and thresholds, printed as its table
        if len(queries) != 1:
            raise DiscoError("--protocol takes one dataset folder")
        model = load_model(model_name or "default", device=device)
        policy = policy_for(model, **settings)
        say = lambda msg: stderr.print(msg, highlight=False)  # noqa: E731
        proto, results = run_protocol(protocol, queries[0], model, warn, say, oxford_scale, policy)
        rows = table_rows(proto, results, approach=f"disco ({model.name})")
        title = f"{proto.dataset}: {model.name}"
        return RowWriter(TABLE_COLUMNS, fmt, digits=2).write(rows, title=title)
    if db_path is None:
        raise PoseFileError("give --db map.db (or --protocol NAME DATASET_FOLDER)")
    paths = scan_paths(queries, scan_format, topic)
    poses_file = file_beside(queries, query_poses)
    if poses_file is None and pose_topic is None:
        raise no_poses_error(paths, "query poses", "--poses")
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, q_poses = posed_scans(paths, poses_file, opts, warn, pose_topic)
    with (
        Map.open(db_path, model=model_name, device=device) as m,
        steps("embedding", len(paths)) as step,
    ):
        policy = policy_for(m.model, **settings)
        ev = multi_session(paths, q_poses, m, radius, topk, scan_format, step, policy=policy)
    run = {
        "protocol": "multi-session",
        **model_run(m.model, policy),
        "database": str(db_path),
        "queries": " ".join(map(str, queries)),
        "query_poses": str(poses_file) if pose_topic is None else pose_topic,
        "radius_m": radius,
        "topk": topk,
    }
    report_and_print(ev, run, report, fmt)
