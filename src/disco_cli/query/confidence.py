"""One confidence per answer: the estimated probability that a row is a true revisit.

A row's distance orders one query's candidates; it does not say how sure the answer
is across queries (a changed place matches worse than an unchanged one, and the right
candidate may still be the best). The confidence combines the cues the query computes
anyway, in a logistic model fitted on the selection worlds only
(`benchmarks/calibrate_confidence.py` fits it, prints what each cue adds and the
reliability table; docs/confidence.md has both):

- place cues (`PlaceCues`, every row): the re-rank distance at its best over the
  query and its views, the signature distance, the row's lead over the best
  candidate at another place, and the yaw's confidence;
- with the layout check of the best few rows (`verification.py`, and every row given a
  pose): the height images' phase-correlation peak and the offset it finds.

Two logistic models, one per amount of evidence (`place`, `checked`); each weighs the
cues that carried from one selection world to another (the ICP fit's did not: it
differs too much between a changed campus and a suburb to say the same thing in both).

A model the calibration does not know (a checkpoint of one's own, Scan Context, the
spectral floor) gets NaN: a probability is only as good as the data it was fitted on.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "PlaceCues",
    "place_cues",
    "place_confidence",
    "checked_confidence",
    "cue_features",
    "calibrated",
    "calibrations",
    "ELSEWHERE_M",
]

# A candidate this far from a row on the map (or, where the map has no poses, this
# many rows away in id order, a sequence's frames) stands at another place: the lead
# is measured against the best of those. 30 m lies beyond every family's true radius
# (1.5 / 3 / 25 m), so a neighbour of the same place never counts against a row.
ELSEWHERE_M = 30.0
ELSEWHERE_ROWS = 30
# Where no candidate stands elsewhere, the lead is this (the largest seen matters less
# than that there is no rival).
LEAD_CAP = 0.5


@dataclass(frozen=True)
class PlaceCues:
    """What one row's place recognition says of it (NaN where the model gives none)."""

    distance: float  # the row's ranking distance (search.ranking_score)
    rerank: float  # the re-rank distance at its best over the query and its views
    rerank_own: float  # the query's own re-rank distance
    signature: float  # the nearest signature distance over the query and its views
    lead: float  # the best other place's distance less this row's, <= LEAD_CAP


def place_cues(
    distance: np.ndarray,
    own: np.ndarray,
    best: np.ndarray,
    signature: np.ndarray,
    poses: np.ndarray | None,
    rows: np.ndarray,
    only: np.ndarray | None = None,
) -> list[PlaceCues]:
    """The cues of each candidate (one order for every array: the candidates'), or of
    the candidates `only` (indices, in that order; every candidate still counts as a
    rival)."""
    d = np.asarray(distance, np.float64)
    n = len(d)
    pick = np.arange(n) if only is None else np.asarray(only, np.int64)
    if n == 0 or len(pick) == 0:
        return []
    far = _elsewhere(poses, np.asarray(rows), n, pick)
    rival = np.where(far, d[None, :], np.inf).min(axis=1)
    lead = np.minimum(rival - d[pick], LEAD_CAP)
    own, best, sig = (np.asarray(a, np.float64)[pick] for a in (own, best, signature))
    return [
        PlaceCues(float(d[j]), float(best[i]), float(own[i]), float(sig[i]), float(lead[i]))
        for i, j in enumerate(pick.tolist())
    ]


def _elsewhere(poses: np.ndarray | None, rows: np.ndarray, n: int, pick: np.ndarray) -> np.ndarray:
    """[len(pick), n]: whether candidate b stands at another place than candidate
    pick[a]."""
    by_rows = np.abs(rows[pick, None].astype(np.int64) - rows[None, :]) > ELSEWHERE_ROWS
    if poses is None:
        return by_rows
    xy = np.asarray(poses, np.float64)[:n, :2]
    known = np.isfinite(xy).all(axis=1)
    apart = np.hypot(*(xy[pick, None, :] - xy[None, :, :]).transpose(2, 0, 1)) > ELSEWHERE_M
    both = known[pick, None] & known[None, :]
    return np.where(both, apart, by_rows)


@dataclass(frozen=True)
class Calibration:
    """A logistic model: p = 1 / (1 + exp(-(bias + sum(weight_k * feature_k))))."""

    bias: float
    weights: dict[str, float]


def cue_features(
    cues: PlaceCues,
    yaw_conf: float,
    layout: Any = None,
    fitness: float = math.nan,
    rmse: float = math.nan,
) -> dict[str, float]:
    """The features the calibrations weigh, by name: the place cues', the layout
    check's (`relative_pose.LayoutCheck`) where given, the ICP fit's where given."""
    out = {
        "rerank": cues.rerank,
        "log_signature": math.log(max(cues.signature, 1e-3)),
        "lead": cues.lead,
        # A model without a yaw confidence: as unsure as a street alike both ways.
        "yaw_conf": yaw_conf if math.isfinite(yaw_conf) else 0.5,
        "view_gain": cues.rerank_own - cues.rerank,
    }
    if layout is not None:
        out["peak"] = layout.peak
        # Metres between the two sensors by the height images: a true revisit stands
        # near; a wrong place's peak lands anywhere (capped: past it all is far).
        out["shift"] = min(layout.shift_m, SHIFT_CAP_M)
        out["flipped"] = float(layout.flipped)
    if math.isfinite(fitness) or math.isfinite(rmse):
        out["fitness"] = fitness if math.isfinite(fitness) else 0.0
        # An early rejection has no rmse worth the name: as bad as the acceptance bound.
        out["rmse"] = min(rmse, RMSE_CAP_M) if math.isfinite(rmse) else RMSE_CAP_M
    return out


SHIFT_CAP_M = 15.0  # relative_pose.PoseConfig.max_translation
RMSE_CAP_M = 0.5


def _probability(cal: Calibration, features: dict[str, float]) -> float:
    z = cal.bias + sum(w * features[k] for k, w in cal.weights.items())
    if not math.isfinite(z):
        return math.nan
    return 1.0 / (1.0 + math.exp(-max(min(z, 40.0), -40.0)))


def _confidence(model: Any, kind: str, features: dict) -> float:
    cal = calibrations().get((str(getattr(model, "fingerprint", "")), kind))
    return math.nan if cal is None else _probability(cal, features)


def calibrated(model: Any) -> bool:
    """Whether `model` has a calibration (its rows get a confidence)."""
    fingerprint = str(getattr(model, "fingerprint", ""))
    return any(key[0] == fingerprint for key in calibrations())


def place_confidence(model: Any, cues: PlaceCues | None, yaw_conf: float) -> float:
    """P(true revisit | the row's place cues) under `model`'s calibration (NaN: none)."""
    if cues is None:
        return math.nan
    return _confidence(model, "place", cue_features(cues, yaw_conf))


def checked_confidence(model: Any, cues: PlaceCues | None, yaw_conf: float, layout: Any) -> float:
    """P(true revisit | the place cues and the layout check)."""
    if cues is None:
        return math.nan
    return _confidence(model, "checked", cue_features(cues, yaw_conf, layout))


# The fitted calibrations, written by `benchmarks/calibrate_confidence.py fit --write`
# beside this module with the worlds, command and figures they came from.
FIT_FILE = Path(__file__).with_name("confidence_fit.json")


@functools.lru_cache(maxsize=1)
def calibrations() -> dict[tuple[str, str], Calibration]:
    """(model fingerprint, kind) -> Calibration, from FIT_FILE (empty without it)."""
    try:
        fit = json.loads(FIT_FILE.read_text())
    except (OSError, ValueError):
        return {}
    out = {}
    for kind in ("place", "checked"):
        if kind in fit:
            c = fit[kind]
            out[(fit["model"], kind)] = Calibration(float(c["bias"]), dict(c["weights"]))
    return out
