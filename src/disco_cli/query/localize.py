"""Localizing a scan against stored scans: the matches, their yaw and the refined pose.

Frames and units, for `Match` here and `Loop` in `loop_detector.py`:

- `T` is T_match<-query, a 4 x 4 float64 rigid transform: a point p (metres) in the
  query sensor's frame is `T @ [p, 1]` in the match sensor's frame. Equivalently the
  query sensor's pose in the match's frame.
- `yaw_deg` is the heading of the query sensor in the match's frame, in (-180, 180]
  (docs/architecture.md). Without a pose it is the place-recognition yaw (about 3
  degree resolution); with one it is the yaw of the refined `T`.
- `roll_deg`, `pitch_deg`, `yaw_deg` with a pose: T's rotation R = Rz(yaw) Ry(pitch)
  Rx(roll) (intrinsic z-y'-x'', the usual vehicle convention), pitch in [-90, 90].
- `yaw_conf`: how sure the place-recognition yaw is, in [0, 1]: 1 - the best other
  heading's correlation peak / the yaw's own (`model/yaw_refine.py`). Low where the place
  looks alike both ways (a street alike on both sides); None for a model without one.
  With a pose it still rates the place-recognition yaw that seeded it.
- `distance`: the score that ranks the matches, smaller is closer, so rows come sorted
  by it (`search.ranking_score`): the re-rank distance (1 - the aligned correlation of
  the feature images, at its best over the query and its views) less 0.3 over the
  signature distance; the signature distance for models that do not re-rank. The snap
  gives the map scan nearest the query the best one's distance (a tie it wins).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from disco_cli.io.poses.geometry import wrap_deg

__all__ = ["Match", "PointCache", "euler_deg", "pose_columns", "surest_first"]


@dataclass(frozen=True, eq=False)  # eq would compare the arrays ambiguously
class Match:
    """One place a query scan matched: its rank and distance, yaw, and with `pose=True`
    the refined pose. Frames and units: the module docstring."""

    rank: int  # 1-based
    match_id: int  # the map's id of the matched scan (1, 2, ... in insertion order)
    name: str  # the matched scan's stored name (its path for maps built from files)
    distance: float
    yaw_deg: float
    T: np.ndarray | None = field(default=None, repr=False)  # 4 x 4 T_match<-query
    fitness: float | None = None  # inlier ratio of the ICP alignment
    rmse: float | None = None  # m, point-to-plane, over the inliers
    accepted: bool | None = None  # whether the pose passes the verification thresholds
    # (None without a pose: not asked for, or the match's scan could not be read)
    reason: str = ""  # why rejected, or why no pose could be estimated
    roll_deg: float | None = None
    pitch_deg: float | None = None
    yaw_conf: float | None = None  # in [0, 1]; None: the model gives none
    # The estimated probability that this is a true revisit (query/confidence.py), with
    # the fit's evidence where the match was checked (`verified`); None: the model has
    # no calibration.
    confidence: float | None = None
    verified: bool = False  # whether the geometric check ran on this match
    cues: Any = field(default=None, repr=False)  # confidence.PlaceCues behind it

    def as_dict(self) -> dict[str, Any]:
        """The match as the columns of `disco query`, plus the pose columns and `T` (as
        nested lists) when it has a pose."""
        row = {"rank": self.rank, "match": self.name, "match_id": self.match_id}
        row.update(distance=self.distance, yaw_deg=self.yaw_deg, yaw_conf=self.yaw_conf)
        row["confidence"] = self.confidence
        return {**row, **pose_columns(self)}

    @property
    def translation(self) -> np.ndarray | None:
        """The query sensor's position in the match's frame (m), or None without a pose."""
        return None if self.T is None else self.T[:3, 3].copy()


def euler_deg(T: np.ndarray) -> tuple[float, float, float]:
    """`(roll, pitch, yaw)` in degrees of T's rotation, R = Rz(yaw) Ry(pitch) Rx(roll);
    yaw in (-180, 180]."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    yaw = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    pitch = math.degrees(math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])))
    roll = math.degrees(math.atan2(R[2, 1], R[2, 2]))
    return wrap_deg(roll), pitch, wrap_deg(yaw)


def pose_fields(rp: Any) -> dict[str, Any]:
    """The refined-pose fields of a `RelativePose` as they go into a Match or a Loop."""
    roll, pitch, yaw = euler_deg(rp.T)
    return {
        "T": np.array(rp.T, dtype=np.float64),
        "fitness": float(rp.fitness),
        "rmse": float(rp.rmse),
        "accepted": bool(rp.accepted),
        "reason": rp.reason,
        "roll_deg": roll,
        "pitch_deg": pitch,
        "yaw_deg": yaw,
    }


class PointCache:
    """The points of the last few scans read, by key (a query's matches and a
    sequence's loops often come back to the same scans)."""

    def __init__(self, read: Callable[[Any], np.ndarray], size: int = 32):
        self.read = read
        self.size = size
        self._cache: OrderedDict = OrderedDict()

    def get(self, key: Any) -> np.ndarray:
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        points = self.read(key)
        self._cache[key] = points
        if len(self._cache) > self.size:
            self._cache.popitem(last=False)
        return points


def surest_first(rows: list[Match], below: float) -> list[Match]:
    """`rows` with the checked row of the highest confidence first, where the first
    row's confidence is below `below` and lower than its; it takes the first's distance
    (a tie-break, as the snap's), so that the rows stay sorted by the distance they
    show. Ranks are renumbered."""
    checked = [j for j, r in enumerate(rows) if r.verified and r.confidence is not None]
    if len(rows) < 2 or not checked:
        return rows
    best = max(checked, key=lambda j: (rows[j].confidence, -j))
    first = rows[0].confidence
    if best == 0 or (first is not None and (rows[best].confidence <= first or first >= below)):
        return rows
    moved = [rows[best], *rows[:best], *rows[best + 1 :]]
    top = min(r.distance for r in rows[: best + 1])
    return [
        replace(r, rank=k + 1, distance=top if k == 0 else r.distance) for k, r in enumerate(moved)
    ]


def as_match(m: Any) -> Match:
    """A search result as a `Match` without a pose."""
    return Match(
        m.rank,
        m.match_id,
        m.path,
        m.distance,
        m.yaw_deg,
        yaw_conf=number_or_none(m.yaw_conf),
        confidence=number_or_none(m.confidence),
        cues=m.cues,
    )


def number_or_none(x: float) -> float | None:
    """`x` as a float, None where it is NaN."""
    return float(x) if math.isfinite(x) else None


def pose_columns(x: Any) -> dict[str, Any]:
    """The output columns of a `Match` or `Loop` with a pose (empty without one):
    refined yaw, roll, pitch, translation, scores, and the full 4 x 4 `T` (row-major,
    nested lists; JSON lines carry it, tables and TSV leave it out)."""
    if x.T is None:
        return {}
    T = np.asarray(x.T)
    return {
        "yaw_deg": x.yaw_deg,
        "roll_deg": x.roll_deg,
        "pitch_deg": x.pitch_deg,
        "dx": float(T[0, 3]),
        "dy": float(T[1, 3]),
        "dz": float(T[2, 3]),
        "fitness": x.fitness,
        "rmse": x.rmse,
        "accepted": x.accepted,
        "reason": x.reason,
        "T": T.tolist(),
    }
