"""Verified candidates: a query's best few rows checked against its geometry.

Place recognition ranks the map's scans by their learned images; it does not look at
where their points lie. Here each of the best `depth` rows gets the layout check
(`relative_pose.layout_check`: the two scans' Cartesian height images phase-correlated
at the recognised yaw, a few milliseconds), and with `pose` every row gets the ICP of
`relative_pose.estimate_relative_pose` as well (tens of milliseconds). Each row
checked gets a confidence with that evidence (`confidence.checked_confidence`); the
others keep their place confidence. Where the first is unsure after its check and a
checked row below it is surer, that row goes first and takes the first's distance (a
tie-break, as the snap's), so the rows stay sorted by the distance they show.

A row whose map scan cannot be read stays unchecked (its place confidence stands;
with `pose`, its `reason` says why it has none).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from disco_cli.errors import DiscoError, ScanReadError
from disco_cli.query import relative_pose
from disco_cli.query.confidence import checked_confidence
from disco_cli.query.localize import Match, as_match, number_or_none, pose_fields, surest_first
from disco_cli.query.query_policy import QueryPolicy

__all__ = ["check_candidates", "check_row"]


def check_candidates(
    model: Any,
    found: list[Any],
    query_points: np.ndarray,
    match_points: Callable[[Any], np.ndarray],
    depth: int,
    *,
    pose: bool = False,
    verify: bool = False,
    config: Any = None,
    promote_below: float = QueryPolicy.check_promotes_below,
) -> list[Match]:
    """`found` (search matches, best first) as `Match`es, the best `depth` checked (all
    of them with `pose`, which adds each one's relative pose); the surest checked row
    first where the first is unsure (`promote_below`, the policy's
    `check_promotes_below`; see the module). `match_points(row)` reads a row's map scan
    (`ScanReadError`: left unchecked). `verify` keeps only rows whose pose is accepted
    (implies `pose`)."""
    pose = pose or verify
    rows = [as_match(m) for m in found]
    for j in range(len(rows) if pose else min(depth, len(rows))):
        rows[j] = check_row(model, rows[j], query_points, match_points, pose, config)
    if verify:
        rows = [r for r in rows if r.accepted]
    return surest_first(rows, promote_below)


def check_row(
    model: Any,
    row: Match,
    query_points: np.ndarray,
    match_points: Callable[[Match], np.ndarray],
    pose: bool,
    config: Any = None,
) -> Match:
    """One row checked: the layout check, and with `pose` its relative pose too."""
    yaw_conf = np.nan if row.yaw_conf is None else row.yaw_conf
    try:
        points = match_points(row)
        layout = relative_pose.layout_check(query_points, points, row.yaw_deg, config)
    except ScanReadError as exc:
        return replace(row, reason=str(exc)) if pose else row
    except DiscoError as exc:
        return replace(row, accepted=False, reason=f"no relative pose ({exc})")
    # A pose's fit adds no confidence of its own (docs/confidence.md): the layout's stands.
    conf = number_or_none(checked_confidence(model, row.cues, yaw_conf, layout))
    if not pose:
        return replace(row, confidence=conf, verified=True)
    try:
        rp = relative_pose.estimate_relative_pose(query_points, points, row.yaw_deg, config)
    except DiscoError as exc:
        return replace(row, accepted=False, reason=f"no relative pose ({exc})")
    return replace(row, **pose_fields(rp), confidence=conf, verified=True)
