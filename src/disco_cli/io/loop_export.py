"""Loop closures written for pose-graph tools: g2o edges, TUM-style lines, CSV.

A loop (`loop_detector.Loop`) is a query scan i and an earlier match scan j with the
relative pose T_match<-query (from `relative_pose.estimate_relative_pose`): a point p
in the query's frame is T p in the match's frame.

- `.g2o`: one `EDGE_SE3:QUAT j i x y z qx qy qz qw` line per loop (from vertex j, the
  match, to vertex i, the query; vertex ids are the scans' 0-based sequence indices),
  followed by the 21 upper-triangular entries of the 6 x 6 information matrix
  (`relative_pose.information_matrix`: scaled by the fitness).
- `.tum`: `t_query t_match x y z qx qy qz qw`, one loop per line, the times in
  seconds (the sequence index when no times are known), after a `#` header line.
- `.csv`: a header and one row per loop with indices, paths, match distance, the
  refined yaw, roll and pitch (degrees, of T), the relative pose (translation and
  quaternion), fitness, rmse, accepted and the rejection reason.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from disco_cli.errors import DiscoError
from disco_cli.io.output_paths import atomic_path, check_output_file
from disco_cli.query.relative_pose import information_matrix

if TYPE_CHECKING:
    from disco_cli.query.loop_detector import Loop

__all__ = ["FORMATS", "check_loop_file", "quaternion", "write_loops"]

FORMATS = (".g2o", ".tum", ".csv")


def quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3 x 3 rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    # Take the largest of the four diagonal combinations for a stable square root.
    cases = [tr, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(cases))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _fmt(v: float) -> str:
    return f"{float(v) + 0.0:.9g}"


def check_loop_file(path: str | Path) -> None:
    """`DiscoError` unless `path` names a loop file type and can be written (checked
    before the work)."""
    if Path(path).suffix.lower() not in FORMATS:
        raise DiscoError(f"{path}: unknown loop file type; use {', '.join(FORMATS)}")
    check_output_file(path, what="the loops")


def write_loops(path: str | Path, loops: Sequence[Loop]) -> int:
    """Write `loops` in the format named by `path`'s extension (.g2o, .tum, .csv);
    `.g2o` takes only the accepted ones. Returns how many were written."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in FORMATS:
        raise DiscoError(
            f"{path}: unknown loop file type {ext or '(none)'}; use {', '.join(FORMATS)}"
        )
    lines: list[str] = []
    if ext == ".g2o":
        loops = [lp for lp in loops if lp.accepted]  # a rejected loop is no constraint
        iu = np.triu_indices(6)
        for lp in loops:
            T = np.asarray(lp.T)
            q = quaternion(T[:3, :3])
            info = information_matrix(lp)[iu]
            fields = [
                "EDGE_SE3:QUAT",
                str(lp.match_index),
                str(lp.query_index),
                *map(_fmt, T[:3, 3]),
                *map(_fmt, q),
                *map(_fmt, info),
            ]
            lines.append(" ".join(fields))
    elif ext == ".tum":
        lines.append("# t_query t_match x y z qx qy qz qw  (T_match<-query)")
        for lp in loops:
            T = np.asarray(lp.T)
            tq = lp.query_time if np.isfinite(lp.query_time) else lp.query_index
            tm = lp.match_time if np.isfinite(lp.match_time) else lp.match_index
            lines.append(
                " ".join(
                    [
                        f"{tq:.6f}",
                        f"{tm:.6f}",
                        *map(_fmt, T[:3, 3]),
                        *map(_fmt, quaternion(T[:3, :3])),
                    ]
                )
            )

    try:
        with atomic_path(path) as tmp:
            _write_lines(tmp, ext, lines, loops)
    except OSError as exc:
        raise DiscoError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return len(loops)


def _write_lines(path: Path, ext: str, lines: list[str], loops: Sequence[Loop]) -> None:
    """The file itself: CSV rows of every loop, else the lines made above."""
    if ext == ".csv":
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(
                [
                    "query_index",
                    "match_index",
                    "query",
                    "match",
                    "distance",
                    "yaw_deg",
                    "roll_deg",
                    "pitch_deg",
                    "x",
                    "y",
                    "z",
                    "qx",
                    "qy",
                    "qz",
                    "qw",
                    "fitness",
                    "rmse",
                    "accepted",
                    "reason",
                ]
            )
            for lp in loops:
                T = np.asarray(lp.T)
                w.writerow(
                    [
                        lp.query_index,
                        lp.match_index,
                        lp.query,
                        lp.match,
                        _fmt(lp.distance),
                        _fmt(lp.yaw_deg),
                        _fmt(lp.roll_deg),
                        _fmt(lp.pitch_deg),
                        *map(_fmt, T[:3, 3]),
                        *map(_fmt, quaternion(T[:3, :3])),
                        _fmt(lp.fitness),
                        _fmt(lp.rmse),
                        str(bool(lp.accepted)).lower(),
                        lp.reason,
                    ]
                )
    else:
        path.write_text("".join(line + "\n" for line in lines))
