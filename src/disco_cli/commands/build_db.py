"""`disco build-db`: embed scans into a map database, one transaction per batch.

Ctrl-C or a crash keeps every finished batch; running the same command again
resumes, skipping the scans already stored (by path as given).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_POSES,
    PANEL_RUN,
    CalibOpt,
    DeviceOpt,
    ExtrinsicOpt,
    MaxTimeGapOpt,
    PosesFormatOpt,
    PoseTopicOpt,
    ScanFormatOpt,
    TopicOpt,
    WorkersOpt,
    pose_options,
)
from disco_cli.console import fail, handle_errors, progress, stderr, warn

if TYPE_CHECKING:
    import numpy as np

PANEL_IN = "Input"


@dataclass
class ScanList:
    """The scans of a build in input order, with pose rows and times (NaN = unknown)."""

    paths: list[str]
    poses: np.ndarray  # [N, 4] x, y, z, yaw
    times: np.ndarray  # [N]
    no_pose: int = 0  # scans a pose file was given for that got no pose


def collect_scans(
    inputs: list[str],
    poses_file: Path | None,
    times_file: Path | None,
    calib: str | None,
    scan_format: str | None = None,
    pose_opts: dict | None = None,
    topic: str | None = None,
    pose_topic: str | None = None,
) -> ScanList:
    """Expand folders, files, bags and `-` (stdin) into one list of scans.

    A folder with a pose file (`disco_cli.poses.find_pose_file`) and `times.txt` beside
    its scans brings them along unless `--poses` / `--times` are given; those cover all
    scans. Poses come from `disco_cli.poses.ScanPoser`; scans left without one are
    named in one warning per pose file and counted in `ScanList.no_pose`.
    Scans in a bag are timed by their header stamps, and posed from the bag's
    `pose_topic` when given (by time, like a pose file).
    """
    import numpy as np

    from disco_cli.pipeline import frame_rows, pose_rows, stdin_paths
    from disco_cli.poses import ScanPoser, find_pose_file, read_times
    from disco_cli.readers import list_scans
    from disco_cli.readers.bags import scan_stamps

    opts = dict(pose_opts or {})
    opts.setdefault("calib", "auto" if calib is None else calib)
    paths: list[str] = []
    poses: list[np.ndarray] = []
    times: list[np.ndarray] = []
    seen: set[str] = set()
    no_pose = 0

    def lidar_rows(group: list[str], pose_file: Path) -> np.ndarray:
        nonlocal no_pose
        T, report = ScanPoser(pose_file, **opts).poses(group)
        if report.warning():
            warn(report.warning())
        no_pose += report.missing
        return pose_rows(T)

    for item in inputs:
        if item == "-":
            group = list(stdin_paths())
        else:
            group = [str(p) for p in list_scans(item, scan_format, topic)]
        group = [p for p in dict.fromkeys(group) if p not in seen]
        seen.update(group)
        n = len(group)
        p_rows, t_rows = np.full((n, 4), np.nan), scan_stamps(group)
        folder = Path(item)
        if item != "-" and folder.is_dir() and group:
            beside = find_pose_file(folder) if poses_file is None else None
            if beside is not None:
                p_rows = lidar_rows(group, beside)
            if times_file is None and (folder / "times.txt").is_file():
                t = read_times(folder / "times.txt")
                t_rows = t[frame_rows(group, len(t), str(folder / "times.txt"))]
        paths += group
        poses.append(p_rows)
        times.append(t_rows)
    all_poses = np.concatenate(poses) if poses else np.empty((0, 4))
    all_times = np.concatenate(times) if times else np.empty(0)
    if poses_file is not None:
        all_poses = lidar_rows(paths, poses_file)
    if times_file is not None:
        t = read_times(times_file)
        all_times = t[frame_rows(paths, len(t), str(times_file))]
    if pose_topic is not None:
        from disco_cli.readers.bags import bag_poses

        T, missing = bag_poses(paths, pose_topic, opts.get("max_time_gap"), opts.get("extrinsic"))
        if missing:
            warn(
                f"{pose_topic}: {len(missing)} of {len(paths)} scans have no pose near their "
                f"stamp (e.g. {missing[0]}); they are left without one"
            )
        no_pose += len(missing)
        all_poses = pose_rows(T)
    return ScanList(paths, all_poses, all_times, no_pose)


@handle_errors
def build_db(
    inputs: Annotated[
        list[str],
        typer.Argument(
            help="Scan folders (KITTI-style DIR/velodyne/ or a folder of scans), scan files, "
            "or - to read scan paths from stdin, one per line.",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path,
        typer.Option(
            "--output", "-o", help="The database file to write (map.db).", rich_help_panel=PANEL_IN
        ),
    ] = Path("map.db"),
    model: Annotated[
        str,
        typer.Option(
            "--model",
            "-m",
            rich_help_panel=PANEL_IN,
            help="default, spectral, scancontext or a checkpoint path.",
        ),
    ] = "default",
    poses: Annotated[
        Optional[Path],
        typer.Option(
            "--poses",
            help="Poses of all scans (KITTI by frame, or by time: --poses-format); "
            "default: the pose file beside each folder's scans.",
            rich_help_panel=PANEL_POSES,
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
            help="Timestamps (s), one per scan; default: times.txt beside each folder's scans.",
            rich_help_panel=PANEL_IN,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    append: Annotated[
        bool,
        typer.Option(
            "--append",
            help="Add these scans to an existing database built from other scans (same model).",
            rich_help_panel=PANEL_IN,
        ),
    ] = False,
    batch: Annotated[
        int,
        typer.Option(
            "--batch",
            min=1,
            max=4096,
            help="Scans per network batch and per transaction.",
            rich_help_panel=PANEL_RUN,
        ),
    ] = 32,
    workers: WorkersOpt = 1,
    device: DeviceOpt = "cpu",
    skip_bad: Annotated[
        bool,
        typer.Option(
            "--skip-bad",
            help="Warn about unreadable scans and go on, instead of stopping at the first.",
            rich_help_panel=PANEL_RUN,
        ),
    ] = False,
) -> None:
    """Build (or resume, or extend) a map database from scans."""
    from disco_cli import __version__
    from disco_cli.database import Database, ModelInfo, ScanBatch
    from disco_cli.errors import DatabaseError
    from disco_cli.model import MODELS, load_model
    from disco_cli.pipeline import check_device, embed_stream, load_stream

    check_device(device)
    fmt = scan_format.value if scan_format is not None else None
    if pose_topic is not None and poses is not None:
        raise fail("give --poses or --pose-topic, not both")
    pose_opts = pose_options(poses_format, calib, extrinsic, max_time_gap)
    scans = collect_scans(inputs, poses, times, calib, fmt, pose_opts, topic, pose_topic)
    if not scans.paths:
        raise fail("no scans given")
    net = load_model(model, device=device)
    info = ModelInfo.of(net)
    # How `disco query` finds the model again: a registry name or a checkpoint's full path.
    source = model if model in MODELS else str(Path(model).resolve())

    db: Database | None = None
    already = 0
    if output.exists():
        db = Database.open(output, writable=True)
        db.check_model(info)
        stored = set(db.paths())
        if not append and not stored.issubset(scans.paths):
            db.close()
            raise DatabaseError(
                output,
                "exists and holds other scans; pass --append to add to it, "
                "or choose another --output",
            )
        already = sum(1 for p in scans.paths if p in stored)
    todo = [i for i, p in enumerate(scans.paths) if db is None or p not in stored]
    if not todo:
        stderr.print(f"{output}: all {len(scans.paths)} scans are in it already")
        if db is not None:
            db.close()
        return

    written, bad = 0, []
    start = time.perf_counter()
    loaded = load_stream(
        (scans.paths[i] for i in todo),
        net.bev_config,
        workers=workers,
        prefetch=max(2 * batch, 4 * workers),
        scan_format=fmt,
    )
    try:
        with progress() as bar:
            task = bar.add_task("build-db", total=len(todo), rate="")
            for chunk in embed_stream(loaded, net, batch):
                for item in chunk.errors:
                    if not skip_bad:
                        raise item.error  # type: ignore[misc]
                    warn(f"skipped: {item.error}")
                    bad.append(item.path)
                if chunk.items:
                    rows = [todo[it.index] for it in chunk.items]
                    part = ScanBatch(
                        paths=[scans.paths[r] for r in rows],
                        signatures=chunk.signatures,
                        features=chunk.features,
                        poses=scans.poses[rows],
                        times=scans.times[rows],
                    )
                    if db is None:
                        db = Database.create(
                            output,
                            info,
                            part,
                            disco_version=__version__,
                            extra_meta={"model_source": source},
                        )
                    else:
                        db.append(part)
                    written += len(rows)
                done = written + len(bad)
                rate = written / max(time.perf_counter() - start, 1e-9)
                bar.update(task, completed=done, rate=f"{rate:.1f} scans/s")
    finally:
        loaded.close()
        if db is not None:
            db.close()
    elapsed = time.perf_counter() - start
    rate = written / max(elapsed, 1e-9)
    msg = f"{output}: wrote {written} scans in {elapsed:.1f} s ({rate:.1f} scans/s)"
    if already:
        msg += f", {already} were in it already"
    if scans.no_pose:
        msg += f", {scans.no_pose} without a pose"
    stderr.print(msg)
    if bad:
        warn(f"{len(bad)} unreadable scans skipped")
    if written == 0 and db is None:
        raise fail(f"{output}: no readable scans; nothing written")
