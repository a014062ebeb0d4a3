"""Loops along one sequence, judged: a family's two sessions joined and fed to `LoopDetector`.

What a SLAM back end sees: one drive after another, each scan searched against the
scans at least `exclude_frames` before it (`disco loops`' default window). A loop is
true where its match lies within `loop_radius` of the query's true position: 3 m, the
radius of `disco gt-loops` and `disco eval-loops` (a relative pose is estimated across
it), or wider where the family's scans are sampled wider: its place spacing (MulRan-like
places every 5 m, with the query run up to 3.5 m off them, so the nearest earlier scan
often stands 3-4.5 m away) or its own radius (Oxford-like submaps, 25 m). A scan has a
true revisit where some scan far enough back lies within it. The rows say,
per scan, what the detector reported with its defaults (`--all` rows: every
candidate, with its confidence, for choosing a threshold).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from disco_cli.evaluation.paper_families import Family, load_run, scan_points
from disco_cli.io.poses import xy_yaw
from disco_cli.query.loop_detector import LoopDetector

__all__ = ["joined_scans", "label_rows", "loop_rows", "loop_summary", "precision_at"]

EXCLUDE_FRAMES = 50  # disco loops' default window
LOOP_TRUE_M = 3.0  # disco gt-loops' and eval-loops' radius


def loop_radius(fam: Family) -> float:
    """Within how many metres a loop's two scans make a true loop (module docstring)."""
    return max(LOOP_TRUE_M, fam.radius, fam.step_m)


def joined_scans(fam: Family, folder: Path, work: Path) -> tuple[list[str], np.ndarray]:
    """(scan files, x y [N, 2]) of sessions 00 then 01 of a world; Oxford-like submaps are
    written under `work` once (the detector reads what a user would hand it)."""
    paths: list[str] = []
    xy = []
    mount = float(json.loads((folder / "world.json").read_text())["sensor"]["mount_height"])
    for k, session in enumerate(("00", "01")):
        files, poses = load_run(folder / session)
        x, y, _ = xy_yaw(poses)
        xy.append(np.stack([x, y], axis=1))
        if not fam.submap:
            paths += [str(p) for p in files]
            continue
        out = work / f"{folder.name}-joined" / session
        out.mkdir(parents=True, exist_ok=True)
        for i, p in enumerate(files):
            target = out / p.name
            if not target.is_file():
                seed = 10**6 * k + i  # as paper_families.evaluate draws them
                scan_points(fam, p, mount, seed).tofile(target)
            paths.append(str(target))
    return paths, np.concatenate(xy)


def loop_rows(
    fam: Family, folder: Path, work: Path, *, min_confidence: Any = "default", **detector: Any
) -> list[dict]:
    """One row per scan of the joined sequence: whether it has a true revisit, and the
    loop the detector reported for it (None), with its confidence, whether it is true,
    and the time the scan took (embedding included)."""
    paths, xy = joined_scans(fam, folder, work)
    options: dict[str, Any] = {"exclude_frames": EXCLUDE_FRAMES, **detector}
    if min_confidence != "default":
        options["min_confidence"] = min_confidence
    det = LoopDetector("default", **options)
    rows = []
    t0 = time.perf_counter()
    for i, loops in enumerate(det.add_files(paths)):
        row: dict[str, Any] = {"scan": i, "ms": round(1000 * (time.perf_counter() - t0), 2)}
        if loops:
            row.update(match=loops[0].match_index, confidence=loops[0].confidence)
        rows.append(row)
        t0 = time.perf_counter()
    return label_rows(rows, xy, loop_radius(fam))


def label_rows(rows: list[dict], xy: np.ndarray, radius: float) -> list[dict]:
    """`rows` (scan, and match where one was reported) judged against the sequence's
    positions `xy`: `has` (a scan at least EXCLUDE_FRAMES back within `radius`), and for
    a loop its `metres` and whether it is `true` (within `radius`). In place; returned."""
    for r in rows:
        back = xy[: max(r["scan"] - EXCLUDE_FRAMES + 1, 0)] - xy[r["scan"]]
        r["has"] = bool(len(back) and np.hypot(*back.T).min() <= radius)
        if "match" in r:
            d = float(np.hypot(*(xy[r["match"]] - xy[r["scan"]])))
            r.update(metres=round(d, 2), true=d <= radius)
    return rows


def loop_summary(rows: list[dict], min_confidence: float | None = None) -> dict[str, Any]:
    """Loops reported (those at or above `min_confidence`, None: as the rows hold them),
    false ones, and recall: the share of scans with a true revisit given a true loop."""
    kept = [r for r in rows if "match" in r and _passes(r, min_confidence)]
    false = sum(not r["true"] for r in kept)
    has = sum(r["has"] for r in rows)
    true = sum(r["true"] and r["has"] for r in kept)
    return {
        "scans": len(rows),
        "with_revisit": has,
        "loops": len(kept),
        "false": false,
        "recall": true / has if has else float("nan"),
        "median_ms": float(np.median([r["ms"] for r in rows])) if rows else float("nan"),
    }


def _passes(row: dict, bar: float | None) -> bool:
    if bar is None:
        return True
    c = row.get("confidence")
    return c is not None and c >= bar


def precision_at(rows: list[dict], bars: np.ndarray) -> list[tuple[float, float, float]]:
    """(bar, precision, recall) of the loops at or above each confidence bar."""
    out = []
    for bar in bars:
        s = loop_summary(rows, float(bar))
        prec = 1.0 - s["false"] / s["loops"] if s["loops"] else 1.0
        out.append((float(bar), prec, s["recall"]))
    return out
