"""`disco gt-loops`: true revisits from the ground-truth poses of KITTI-style sequences.

With several sequences, every later one is queried against every earlier one;
with one, frames at least `--exclude-frames` apart are paired. Each row gives the
distance (m) and the relative yaw (deg, the query's heading in the match's frame).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from disco_cli.commands.options import OutputFormatOpt, calib_file, calib_option
from disco_cli.console import RowWriter, fail, handle_errors, stderr

COLUMNS = ["query_seq", "query", "match_seq", "match", "distance_m", "yaw_deg"]


@handle_errors
def gt_loops(
    seqs: Annotated[
        list[Path],
        typer.Argument(
            help="KITTI-style folders, each with poses.txt.", exists=True, file_okay=False
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
    calib: Annotated[
        Optional[Path],
        calib_option(
            "KITTI calib.txt for every sequence's camera poses; default: the calib.txt "
            "beside each poses.txt; none: use the poses as they are."
        ),
    ] = None,
    fmt: OutputFormatOpt = None,
) -> None:
    """List true revisit pairs (ground truth) within or between sequences."""
    from disco_cli.poses import (
        gt_pairs,
        gt_pairs_within,
        pair_distances,
        read_kitti_poses,
        relative_yaw_deg,
    )

    if not seqs:
        raise fail("give at least one sequence folder")
    poses = []
    for seq in seqs:
        if not (seq / "poses.txt").is_file():
            raise fail(f"{seq}: no poses.txt")
        poses_file = seq / "poses.txt"
        poses.append(read_kitti_poses(poses_file, calib=calib_file(calib, poses_file)))

    writer = RowWriter(COLUMNS, fmt, digits=3)
    if len(seqs) == 1:
        jobs = [(0, 0, gt_pairs_within(poses[0], radius, exclude_frames))]
    else:
        jobs = [
            (q, m, gt_pairs(poses[q], poses[m], radius)) for q in range(len(seqs)) for m in range(q)
        ]
    total = 0
    for q, m, pairs in jobs:
        if len(pairs) == 0:
            continue
        total += len(pairs)
        dist = pair_distances(poses[q], poses[m], pairs)
        yaw = relative_yaw_deg(poses[m][pairs[:, 1]], poses[q][pairs[:, 0]])
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
