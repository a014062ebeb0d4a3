"""`disco eval` and `disco eval-loops`: place-recognition metrics against ground-truth poses.

`eval` is the paper's multi-session protocol: scans of one session are queried against
a database of another; the database's stored poses are the ground truth. `eval-loops`
is the single-sequence loop-closure protocol used on KITTI: every scan against the
scans at least an exclusion window before it. Definitions: docs/evaluation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from disco_cli.commands.options import (
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    OxfordScaleOpt,
    PosesFormatOpt,
    ProtocolOpt,
    RerankOpt,
    ScanFormatOpt,
    apply_rerank,
    pose_options,
)
from disco_cli.console import OutputFormat, handle_errors

if TYPE_CHECKING:
    import numpy as np

PANEL_INPUT = "Input"
PANEL_PROTOCOL = "Protocol"
PANEL_OUTPUT = "Output"


def _scan_paths(inputs: list[Path], scan_format: str | None) -> list[Path]:
    from disco_cli.errors import ScanReadError
    from disco_cli.readers import list_scans

    paths: list[Path] = []
    for item in inputs:
        paths += list_scans(item, format=scan_format)
    if not paths:
        raise ScanReadError(", ".join(map(str, inputs)), "no scans found")
    return paths


def _auto_file(inputs: list[Path], given: Path | None, name: str | None = None) -> Path | None:
    """`given`, else NAME (default: the pose file, `disco_cli.poses.find_pose_file`) beside
    the scans when a single folder was given."""
    if given is not None:
        return given
    if len(inputs) != 1 or not inputs[0].is_dir():
        return None
    if name is None:
        from disco_cli.poses import find_pose_file

        return find_pose_file(inputs[0])
    return inputs[0] / name if (inputs[0] / name).is_file() else None


def embed_scans(
    paths: list[Path], model: Any, scan_format: str | None, batch: int = 32, workers: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """(signatures [N, D], features [N, ...]) of the scans, in order; reading and voxelizing
    overlap the network (disco_cli.pipeline). Every scan must load: an unreadable one stops
    the evaluation, since the scans pair up with the poses by position."""
    import numpy as np

    from disco_cli.console import progress
    from disco_cli.pipeline import embed_stream, load_stream

    sigs, feats = [], []
    with progress(transient=True) as bar:
        task = bar.add_task("embedding", total=len(paths), rate="")
        loaded = load_stream(map(str, paths), model.bev_config, workers, scan_format=scan_format)
        for out in embed_stream(loaded, model, batch):
            if out.errors:
                raise out.errors[0].error
            sigs.append(out.signatures)
            feats.append(out.features)
            bar.advance(task, len(out.items))
    return np.concatenate(sigs), np.concatenate(feats)


def _load_poses(
    paths: list[Path], poses_file: Path, pose_opts: dict
) -> tuple[list[Path], np.ndarray]:
    """The scans that have a pose and their LiDAR poses (`disco_cli.poses.ScanPoser`);
    the others are named in one warning and left out of the evaluation."""
    import numpy as np

    from disco_cli.console import warn
    from disco_cli.errors import PoseFileError
    from disco_cli.poses import ScanPoser

    T, report = ScanPoser(poses_file, **pose_opts).poses(paths)
    if report.warning():
        warn(report.warning() + " and left out of the evaluation")
    keep = np.isfinite(T[:, 0, 3])
    if not keep.any():
        raise PoseFileError(f"{poses_file}: none of the {len(paths)} scans has a pose")
    return [p for p, k in zip(paths, keep) if k], T[keep]


def _model_for(db: Any, name: str | None, device: str) -> Any:
    """The model the database was built with (or the one asked for, which must match)."""
    from disco_cli.database import ModelInfo
    from disco_cli.errors import ModelError
    from disco_cli.model import MODELS, load_model

    if name is None:
        name = db.model.name
        if name not in MODELS:
            raise ModelError(
                f"{db.path}: built with model '{name}', which is not a built-in name; "
                "pass its checkpoint with --model"
            )
    model = load_model(name, device=device)
    db.check_model(ModelInfo.of(model))
    return model


def _report_and_print(
    ev: Any, run: dict[str, Any], report: Path | None, fmt: OutputFormat | None
) -> None:
    from disco_cli.console import stderr
    from disco_cli.evaluation.report import print_metrics, write_report

    if report is not None:
        written = write_report(report, ev, run)
        stderr.print(f"wrote {len(written)} files to {report}", highlight=False)
    print_metrics(ev.metrics, fmt, title=f"{run.get('protocol')}: {run.get('model')}")


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


# Options shared by both commands.
RadiusOpt = Annotated[
    float,
    typer.Option(
        "--radius",
        min=0.0,
        help="True match within this many metres.",
        rich_help_panel=PANEL_PROTOCOL,
    ),
]
ReportOpt = Annotated[
    Optional[Path],
    typer.Option(
        "--report",
        help="Write metrics.json, curves.json, summary.md and PNG plots into this folder.",
        rich_help_panel=PANEL_OUTPUT,
    ),
]
FormatOpt = Annotated[
    Optional[OutputFormat],
    typer.Option(
        "--format",
        help="table (default on a terminal), tsv (default in a pipe) or jsonl (one object).",
        rich_help_panel=PANEL_OUTPUT,
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
        Optional[Path],
        typer.Option(
            "--db", help="Map database of another session, with poses.", rich_help_panel=PANEL_INPUT
        ),
    ] = None,
    protocol: ProtocolOpt = None,
    oxford_scale: OxfordScaleOpt = None,
    query_poses: Annotated[
        Optional[Path],
        typer.Option(
            "--query-poses",
            help="Poses of the queries; default: the pose file in a single query folder.",
            rich_help_panel=PANEL_INPUT,
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    scan_format: ScanFormatOpt = None,
    model_name: Annotated[
        Optional[str],
        typer.Option(
            "--model",
            help="Model name or checkpoint; default: the one that built the database.",
            rich_help_panel=PANEL_PROTOCOL,
        ),
    ] = None,
    radius: RadiusOpt = 3.0,
    topk: Annotated[
        int,
        typer.Option(
            "--topk", min=1, help="Recall@1..N up to this N.", rich_help_panel=PANEL_PROTOCOL
        ),
    ] = 25,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    report: ReportOpt = None,
    fmt: FormatOpt = None,
) -> None:
    """Multi-session evaluation: Recall@N, Recall@1%, PR AUC, F1max, yaw error vs a database."""
    import numpy as np

    from disco_cli.database import Database
    from disco_cli.errors import DatabaseError, PoseFileError
    from disco_cli.evaluation.metrics import (
        one_percent_n,
        retrieval_evaluation,
        within_radius,
        wrap_deg,
    )
    from disco_cli.poses import xy_yaw
    from disco_cli.search import SignatureIndex, match_queries, rerank_depth

    if protocol is not None:
        return _run_protocol(protocol, queries, model_name, device, rerank, fmt, oxford_scale)
    if db_path is None:
        raise PoseFileError("give --db map.db (or --protocol NAME DATASET_FOLDER)")
    paths = _scan_paths(queries, scan_format)
    poses_file = _auto_file(queries, query_poses)
    if poses_file is None:
        raise PoseFileError("no query poses: give --query-poses FILE (or a folder with poses.txt)")
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, q_poses = _load_poses(paths, poses_file, opts)
    with Database.open(db_path) as db:
        model = _model_for(db, model_name, device)
        apply_rerank(model, rerank)
        db_poses, _ = db.poses()
        if not np.isfinite(db_poses[:, :2]).all():
            raise DatabaseError(db.path, "some scans have no pose; build it with --poses")
        ids, db_sigs = db.signatures()
        sigs, feats = embed_scans(paths, model, scan_format)
        depth = max(topk, one_percent_n(len(ids)))
        matches = match_queries(SignatureIndex(db_sigs), ids, db, model, sigs, feats, depth)

    retrieved = np.full((len(paths), depth), -1, np.int64)
    distances = np.full((len(paths), depth), np.inf)
    yaw_est = np.full(len(paths), np.nan)
    for i, found in enumerate(matches):
        for m in found:
            retrieved[i, m.rank - 1], distances[i, m.rank - 1] = m.row, m.distance
        if found:
            yaw_est[i] = found[0].yaw_deg
    qx, qy, qyaw = xy_yaw(q_poses)
    truth = within_radius(np.c_[qx, qy], db_poses[:, :2], radius)
    top1 = np.maximum(retrieved[:, 0], 0)
    # Ground-truth yaw of T_match^-1 T_query for planar poses: the heading difference.
    yaw_true = wrap_deg(np.degrees(qyaw - db_poses[top1, 3]))
    ev = retrieval_evaluation(retrieved, distances, truth, yaw_est, yaw_true)
    # The search went deep enough for recall@1%; report recall@N up to the N asked for.
    ev.metrics["recall@N"] = ev.metrics["recall@N"][:topk]
    ev.metrics["topk"] = topk
    ev.recall_curve = ev.recall_curve[:topk]
    run = {
        "protocol": "multi-session",
        "model": model.name,
        "fingerprint": model.fingerprint,
        "rerank": rerank_depth(model),
        "database": str(db_path),
        "queries": " ".join(map(str, queries)),
        "query_poses": str(poses_file),
        "radius_m": radius,
        "topk": topk,
    }
    _report_and_print(ev, run, report, fmt)


@handle_errors
def evaluate_loops(
    sequence: Annotated[
        list[Path],
        typer.Argument(
            help="One sequence: a folder (velodyne/ layout) or its scans in order.",
            show_default=False,
        ),
    ],
    poses: Annotated[
        Optional[Path],
        typer.Option(
            "--poses",
            help="Poses; default: the pose file in the folder.",
            rich_help_panel=PANEL_INPUT,
        ),
    ] = None,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    max_time_gap: MaxTimeGapOpt = None,
    times: Annotated[
        Optional[Path],
        typer.Option(
            "--times",
            help="Timestamps, one per scan; default: times.txt in the folder.",
            rich_help_panel=PANEL_INPUT,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    model_name: Annotated[
        str,
        typer.Option(
            "--model",
            help="default, spectral, scancontext or a checkpoint path.",
            rich_help_panel=PANEL_PROTOCOL,
        ),
    ] = "default",
    radius: RadiusOpt = 3.0,
    exclude_seconds: Annotated[
        Optional[float],
        typer.Option(
            "--exclude-seconds",
            min=0.0,
            help="Search only scans at least this long before (default 30; needs times).",
            rich_help_panel=PANEL_PROTOCOL,
        ),
    ] = None,
    exclude_frames: Annotated[
        Optional[int],
        typer.Option(
            "--exclude-frames",
            min=1,
            help="Search only scans at least N frames before.",
            rich_help_panel=PANEL_PROTOCOL,
        ),
    ] = None,
    device: DeviceOpt = "cpu",
    rerank: RerankOpt = None,
    report: ReportOpt = None,
    fmt: FormatOpt = None,
) -> None:
    """Loop closure along one sequence: precision-recall, F1max, recall at 100% precision."""
    import numpy as np

    from disco_cli.database import MatchRows
    from disco_cli.errors import DiscoError, PoseFileError
    from disco_cli.evaluation.metrics import loop_evaluation, within_radius
    from disco_cli.model import load_model
    from disco_cli.pipeline import frame_rows
    from disco_cli.poses import read_times, relative_yaw_deg
    from disco_cli.search import SignatureIndex, match_queries, rerank_depth

    if exclude_seconds is not None and exclude_frames is not None:
        raise DiscoError("give --exclude-seconds or --exclude-frames, not both")
    paths = _scan_paths(sequence, scan_format)
    poses_file = _auto_file(sequence, poses)
    if poses_file is None:
        raise PoseFileError("no poses: give --poses FILE (or a folder with poses.txt)")
    all_paths = paths
    opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    paths, T = _load_poses(paths, poses_file, opts)
    n = len(paths)
    if exclude_frames is not None:
        # Scan i searches scans 0 .. i - N.
        limit = np.maximum(np.arange(n) - exclude_frames + 1, 0)
        exclusion = f"{exclude_frames} frames"
    else:
        seconds = 30.0 if exclude_seconds is None else exclude_seconds
        times_file = _auto_file(sequence, times, "times.txt")
        if times_file is None:
            raise PoseFileError("no times: give --times FILE or use --exclude-frames N")
        t = read_times(times_file)
        # One row per scan, or by frame number (the KITTI rule), for the scans with a pose.
        t = t[frame_rows(list(map(str, all_paths)), len(t), str(times_file))]
        kept = set(paths)
        t = t[[p in kept for p in all_paths]]
        if np.any(np.diff(t) < 0):
            raise PoseFileError(f"{times_file}: times go backwards")
        limit = np.searchsorted(t, t - seconds, side="right")
        exclusion = f"{seconds:g} s"

    model = load_model(model_name, device=device)
    apply_rerank(model, rerank)
    sigs, feats = embed_scans(paths, model, scan_format)

    class _Memory:
        """The scans of this run, standing in for a database in `match_queries`."""

        def rows(self, ids: np.ndarray) -> MatchRows:
            ids = np.asarray(ids, np.int64)
            no_pose = np.full((len(ids), 4), np.nan)
            return MatchRows(ids, [str(paths[i]) for i in ids], no_pose, feats[ids])

    queries = np.flatnonzero(limit > 0)
    matches = match_queries(
        SignatureIndex(sigs),
        np.arange(n),
        _Memory(),
        model,
        sigs[queries],
        feats[queries],
        1,
        limit=limit[queries],
    )
    xy = T[:, :2, 3]
    near = within_radius(xy[queries], xy, radius)
    near &= np.arange(n)[None, :] < limit[queries][:, None]
    has_true = near.any(axis=1)
    dist = np.full(len(queries), np.nan)
    top = np.zeros(len(queries), np.int64)
    yaw_est = np.full(len(queries), np.nan)
    for i, found in enumerate(matches):
        if found:
            dist[i], top[i], yaw_est[i] = found[0].distance, found[0].row, found[0].yaw_deg
    correct = np.isfinite(dist) & near[np.arange(len(queries)), top]
    yaw_true = relative_yaw_deg(T[top], T[queries])
    ev = loop_evaluation(dist, correct, has_true, yaw_est, yaw_true)
    run = {
        "protocol": "loop-closure",
        "model": model.name,
        "fingerprint": model.fingerprint,
        "rerank": rerank_depth(model),
        "sequence": " ".join(map(str, sequence)),
        "poses": str(poses_file),
        "radius_m": radius,
        "exclusion": exclusion,
        "num_scans": n,
    }
    _report_and_print(ev, run, report, fmt)
