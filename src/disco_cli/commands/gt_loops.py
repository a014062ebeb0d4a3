"""`disco gt-loops`: true revisits from the ground-truth poses of KITTI-style sequences.

With several sequences, every later one is queried against every earlier one;
with one, frames at least `--exclude-frames` apart are paired. Each row gives the
distance (m) and the relative yaw (deg, the query's heading in the match's frame).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from disco_cli.commands.options import (
    CalibOpt,
    ExtrinsicOpt,
    OutputFormatOpt,
    PosesFormatOpt,
    pose_options,
)
from disco_cli.runtime.console import RowWriter, fail, handle_errors, stderr

COLUMNS = ["query_seq", "query", "match_seq", "match", "distance_m", "yaw_deg"]


@handle_errors
def gt_loops(
    seqs: Annotated[
        list[Path],
        typer.Argument(
            help="Sequence folders, each with its pose file (poses.txt, global_pose.csv, ...).",
            exists=True,
            file_okay=False,
        ),
    ],
    radius: Annotated[float, typer.Option("--radius", min=0.0, help="Revisit radius (m).")] = 3.0,
    exclude_frames: Annotated[
        int,
        typer.Option(
            "--exclude-frames",
            min=1,
            help="Within one sequence: pair frames at least this far apart.",
        ),
    ] = 50,
    poses_format: PosesFormatOpt = None,
    calib: CalibOpt = None,
    extrinsic: ExtrinsicOpt = None,
    fmt: OutputFormatOpt = None,
) -> None:
    """List true revisit pairs (ground truth) within or between sequences."""
    # deferred: numpy and the pose readers load when the command runs, not for --help
    from disco_cli.io.poses import find_pose_file, read_poses, revisit_pairs

    if not seqs:
        raise fail("give at least one sequence folder")
    opts = pose_options(poses_format, calib, extrinsic, None)
    del opts["max_time_gap"]
    poses = []
    for seq in seqs:
        found = find_pose_file(seq)
        if found is None:
            raise fail(f"{seq}: no poses.txt (nor global_pose.csv, groundtruth_*.csv)")
        # Every row of the pose file, in the LiDAR's frame; indices are the file's rows.
        poses.append(read_poses(found, **opts)[1])

    writer = RowWriter(COLUMNS, fmt, digits=3)
    total = 0
    for q, m, pairs, dist, yaw in revisit_pairs(poses, radius, exclude_frames):
        total += len(pairs)
        rows = [
            {
                "query_seq": str(seqs[q]),
                "query": int(i),
                "match_seq": str(seqs[m]),
                "match": int(j),
                "distance_m": float(d),
                "yaw_deg": float(y),
            }
            for (i, j), d, y in zip(pairs, dist, yaw)
        ]
        writer.write(rows, title=f"{seqs[q]} -> {seqs[m]}: {len(rows)} revisit pairs")
    if total == 0:
        writer.write([])  # the header: "no revisit" is an answer too
    stderr.print(f"{total} revisit pairs within {radius:g} m", soft_wrap=True)
