"""`disco build-db`: embed scans into a map database, one transaction per batch.

Ctrl-C or a crash keeps every finished batch; running the same command again
resumes, skipping the scans already stored (by absolute path).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from disco_cli.commands.options import (
    PANEL_RUN,
    DeviceOpt,
    ScanFormatOpt,
    WorkersOpt,
    model_option,
    output_option,
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


def collect_scans(
    inputs: list[str],
    poses_file: Path | None,
    times_file: Path | None,
    calib: Path | None,
    scan_format: str | None = None,
) -> ScanList:
    """Expand folders, files and `-` (stdin) into one list of scans.

    A folder with `poses.txt` / `times.txt` (and `calib.txt`) beside its scans brings
    them along unless `--poses` / `--times` are given; those cover all scans in order.
    """
    import numpy as np

    from disco_cli.pipeline import frame_rows, pose_rows, stdin_paths
    from disco_cli.poses import read_kitti_poses, read_times
    from disco_cli.readers import list_scans

    paths: list[str] = []
    poses: list[np.ndarray] = []
    times: list[np.ndarray] = []
    seen: set[str] = set()
    for item in inputs:
        if item == "-":
            group = list(stdin_paths())
        else:
            group = [str(p) for p in list_scans(item, scan_format)]
        group = [p for p in dict.fromkeys(group) if p not in seen]
        seen.update(group)
        n = len(group)
        p_rows, t_rows = np.full((n, 4), np.nan), np.full(n, np.nan)
        folder = Path(item)
        if item != "-" and folder.is_dir() and group:
            if poses_file is None and (folder / "poses.txt").is_file():
                beside = folder / "calib.txt"
                auto_calib = calib or (beside if beside.is_file() else None)
                T = read_kitti_poses(folder / "poses.txt", auto_calib)
                p_rows = pose_rows(T)[frame_rows(group, len(T), str(folder / "poses.txt"))]
            if times_file is None and (folder / "times.txt").is_file():
                t = read_times(folder / "times.txt")
                t_rows = t[frame_rows(group, len(t), str(folder / "times.txt"))]
        paths += group
        poses.append(p_rows)
        times.append(t_rows)
    all_poses = np.concatenate(poses) if poses else np.empty((0, 4))
    all_times = np.concatenate(times) if times else np.empty(0)
    if poses_file is not None:
        T = read_kitti_poses(poses_file, calib)
        all_poses = pose_rows(T)[frame_rows(paths, len(T), str(poses_file))]
    if times_file is not None:
        t = read_times(times_file)
        all_times = t[frame_rows(paths, len(t), str(times_file))]
    return ScanList(paths, all_poses, all_times)


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
        Path, output_option("The database file to write (map.db).", panel=PANEL_IN)
    ] = Path("map.db"),
    model: Annotated[
        str, model_option("default, spectral, scancontext or a checkpoint path.", panel=PANEL_IN)
    ] = "default",
    poses: Annotated[
        Optional[Path],
        typer.Option(
            "--poses",
            help="KITTI poses (3 x 4 per line) of all scans, "
            "in order; default: poses.txt beside each folder's scans.",
            rich_help_panel=PANEL_IN,
        ),
    ] = None,
    calib: Annotated[
        Optional[Path],
        typer.Option(
            "--calib",
            help="KITTI calib.txt: turns camera poses into LiDAR poses.",
            rich_help_panel=PANEL_IN,
        ),
    ] = None,
    times: Annotated[
        Optional[Path],
        typer.Option(
            "--times",
            help="Timestamps (s), one per scan; default: times.txt beside each folder's scans.",
            rich_help_panel=PANEL_IN,
        ),
    ] = None,
    scan_format: ScanFormatOpt = None,
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
    from disco_cli.database import Database, ModelInfo, ScanBatch, stored_paths
    from disco_cli.errors import DatabaseError
    from disco_cli.model import MODELS, load_model
    from disco_cli.pipeline import check_device, embed_stream, load_stream

    check_device(device)
    fmt = scan_format.value if scan_format is not None else None
    scans = collect_scans(inputs, poses, times, calib, fmt)
    if not scans.paths:
        raise fail("no scans given")
    # Stored absolute, with the path relative to the database beside it, so that the
    # map can be read from any directory and moved as a whole (docs/database.md).
    absolute, rel_paths = stored_paths(scans.paths, output)
    seen: dict[str, int] = {}
    for i, p in enumerate(absolute):
        seen.setdefault(p, i)
    first = list(seen.values())
    if len(first) < len(absolute):  # two spellings of one file: keep the first
        scans = ScanList([scans.paths[i] for i in first], scans.poses[first], scans.times[first])
        absolute, rel_paths = [absolute[i] for i in first], [rel_paths[i] for i in first]
    net = load_model(model, device=device)
    info = ModelInfo.of(net)
    # How `disco query` finds the model again: a registry name or a checkpoint's full path.
    source = model if model in MODELS else str(Path(model).resolve())

    db: Database | None = None
    already = 0
    if output.exists():
        db = Database.open(output, writable=True)
        db.check_model(info)
        # An older database may hold relative paths: they count from here, as before.
        stored = {os.path.abspath(p) for p in db.paths()}
        if not append and not stored.issubset(absolute):
            db.close()
            raise DatabaseError(
                output,
                "exists and holds other scans; pass --append to add to it, "
                "or choose another --output",
            )
        already = sum(1 for p in absolute if p in stored)
    todo = [i for i, p in enumerate(absolute) if db is None or p not in stored]
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
                        paths=[absolute[r] for r in rows],
                        rel_paths=[rel_paths[r] for r in rows],
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
    except KeyboardInterrupt:
        # Every committed batch is safe (one transaction each); say so, and how to go on.
        held = already + written
        if db is None and output.exists():
            # Interrupted while the new file, its first batch committed, was being opened.
            try:
                with Database.open(output, verify=False) as fresh:
                    held = len(fresh)
            except DatabaseError:
                pass
        if db is None and not output.exists():
            stderr.print(f"interrupted: nothing written; {output} was not created", soft_wrap=True)
        else:
            stderr.print(
                f"interrupted: {output} holds {held} of the {len(scans.paths)} "
                "scans given, safely stored; run the same command again to resume",
                soft_wrap=True,
            )
        raise typer.Exit(130) from None
    finally:
        loaded.close()
        if db is not None:
            db.close()
    elapsed = time.perf_counter() - start
    rate = written / max(elapsed, 1e-9)
    msg = f"{output}: wrote {written} scans in {elapsed:.1f} s ({rate:.1f} scans/s)"
    if already:
        msg += f", {already} were in it already"
    stderr.print(msg)
    if bad:
        warn(f"{len(bad)} unreadable scans skipped")
    if written == 0 and db is None:
        raise fail(f"{output}: no readable scans; nothing written")
