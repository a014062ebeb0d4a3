"""Place-recognition metrics in plain NumPy: recall@N, precision-recall, AUC, F1max, yaw error.

Every function takes arrays that the caller has already worked out from a search
(which database entries came back, at which distance) and the ground truth (which
of them lie within the radius); nothing here knows about scans, models or files.
The exact definitions are in docs/evaluation.md; the docstrings repeat them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The one angle wrap of the package, where evaluation code has long imported it from.
from disco_cli.io.poses.geometry import wrap_deg  # noqa: F401


def yaw_errors_deg(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Absolute yaw errors in [0, 180] degrees, the short way around the circle."""
    return np.abs(wrap_deg(np.asarray(estimated, np.float64) - np.asarray(truth, np.float64)))


def yaw_error_stats(errors: np.ndarray) -> dict[str, float]:
    """Mean, population std and median of absolute yaw errors (NaN when there are none)."""
    errors = np.abs(np.asarray(errors, dtype=np.float64))
    if errors.size == 0:
        nan = float("nan")
        return {"yaw_err_mean_deg": nan, "yaw_err_std_deg": nan, "yaw_err_median_deg": nan}
    return {
        "yaw_err_mean_deg": float(errors.mean()),
        "yaw_err_std_deg": float(errors.std()),
        "yaw_err_median_deg": float(np.median(errors)),
    }


def within_radius(query_xy: np.ndarray, db_xy: np.ndarray, radius: float) -> np.ndarray:
    """[Q, M] bool: which database positions lie within `radius` metres of each query (x, y)."""
    query_xy = np.asarray(query_xy, np.float64).reshape(-1, 2)
    db_xy = np.asarray(db_xy, np.float64).reshape(-1, 2)
    out = np.empty((len(query_xy), len(db_xy)), dtype=bool)
    # Chunked so that a 10k x 10k ground truth does not need 1.6 GB of float64 at once.
    for start in range(0, len(query_xy), 1024):
        block = query_xy[start : start + 1024, None, :] - db_xy[None, :, :]
        out[start : start + 1024] = np.einsum("qmk,qmk->qm", block, block) <= radius * radius
    return out


def retrieval_correct(retrieved: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[Q, K] bool: whether each retrieved database index is a true match.

    `retrieved` holds database indices, -1 where a query got fewer than K results;
    `truth` is the [Q, M] matrix from `within_radius`.
    """
    retrieved = np.asarray(retrieved, dtype=np.int64)
    truth = np.asarray(truth, dtype=bool)
    if retrieved.ndim != 2 or truth.ndim != 2 or len(retrieved) != len(truth):
        raise ValueError(f"retrieved {retrieved.shape} and truth {truth.shape} do not pair up")
    valid = retrieved >= 0
    rows = np.broadcast_to(np.arange(len(retrieved))[:, None], retrieved.shape)
    return valid & truth[rows, np.where(valid, retrieved, 0)]


def recall_at_n(correct: np.ndarray, has_true: np.ndarray) -> np.ndarray:
    """[K] recall@1..K: the fraction of queries that have a true match in the database
    for which at least one of the first n results is a true match.

    NaN everywhere when no query has a true match.
    """
    correct = np.asarray(correct, dtype=bool)
    has_true = np.asarray(has_true, dtype=bool)
    n_pos = int(has_true.sum())
    if n_pos == 0:
        return np.full(correct.shape[1], np.nan)
    hit_by_n = np.logical_or.accumulate(correct[has_true], axis=1)
    return hit_by_n.sum(axis=0) / n_pos


def one_percent_n(db_size: int) -> int:
    """The N of recall@1%: 1 % of the database size, rounded, at least 1 (PointNetVLAD's rule)."""
    return max(1, int(round(db_size / 100.0)))


def recall_at_one_percent(correct: np.ndarray, has_true: np.ndarray, db_size: int) -> float:
    """Recall@N with N = `one_percent_n(db_size)`; the results must reach that deep."""
    n = one_percent_n(db_size)
    correct = np.asarray(correct, dtype=bool)
    if correct.shape[1] < n:
        raise ValueError(f"recall@1% needs the top {n} results, got {correct.shape[1]}")
    return float(recall_at_n(correct[:, :n], has_true)[-1])


@dataclass
class PRCurve:
    """Precision and recall of the top-1 result as its distance threshold grows.

    At threshold t a query whose top-1 distance is <= t is accepted (a positive
    prediction): a true positive when that top-1 is a true match, otherwise a false
    positive (queries without any true match count here too). Recall is TP over the
    queries that have a true match; precision is TP / (TP + FP).
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    n_positive: int

    @property
    def auc(self) -> float:
        """Area under the curve, step-wise (average precision): sum (R_k - R_{k-1}) P_k, R_0 = 0."""
        if self.n_positive == 0 or self.thresholds.size == 0:
            return float("nan") if self.n_positive == 0 else 0.0
        steps = np.diff(np.concatenate([[0.0], self.recall]))
        return float(np.sum(steps * self.precision))

    @property
    def f1(self) -> np.ndarray:
        p, r = self.precision, self.recall
        denom = p + r
        return np.divide(2 * p * r, denom, out=np.zeros_like(denom), where=denom > 0)

    @property
    def f1_max(self) -> float:
        """The best F1 = 2PR / (P + R) over all thresholds (0 when nothing is ever right)."""
        if self.n_positive == 0:
            return float("nan")
        return float(self.f1.max()) if self.thresholds.size else 0.0

    @property
    def f1_max_threshold(self) -> float:
        if self.n_positive == 0 or self.thresholds.size == 0:
            return float("nan")
        return float(self.thresholds[int(np.argmax(self.f1))])

    @property
    def recall_at_full_precision(self) -> float:
        """The largest recall reached while precision is still exactly 1 (0 if never)."""
        if self.n_positive == 0:
            return float("nan")
        full = self.precision >= 1.0
        return float(self.recall[full].max()) if full.any() else 0.0


def precision_recall(
    top1_distance: np.ndarray, top1_correct: np.ndarray, has_true: np.ndarray
) -> PRCurve:
    """The precision-recall curve over the top-1 distance threshold (see `PRCurve`).

    The thresholds are the distinct finite top-1 distances, ascending; tied
    distances enter together. A query with no result (distance NaN or inf) is
    never accepted.
    """
    dist = np.asarray(top1_distance, dtype=np.float64)
    correct = np.asarray(top1_correct, dtype=bool)
    has_true = np.asarray(has_true, dtype=bool)
    if not (dist.shape == correct.shape == has_true.shape) or dist.ndim != 1:
        raise ValueError("top1_distance, top1_correct and has_true must be 1-D of one length")
    n_pos = int(has_true.sum())
    finite = np.isfinite(dist)
    dist, correct = dist[finite], correct[finite]
    order = np.argsort(dist, kind="stable")
    dist, correct = dist[order], correct[order]
    tp = np.cumsum(correct)
    fp = np.cumsum(~correct)
    # Keep the last index of each run of equal distances: ties are accepted together.
    last = np.flatnonzero(np.append(dist[1:] != dist[:-1], True)) if dist.size else np.zeros(0, int)
    tp, fp = tp[last].astype(np.float64), fp[last].astype(np.float64)
    precision = tp / np.maximum(tp + fp, 1.0)
    recall = tp / n_pos if n_pos else np.full_like(tp, np.nan)
    return PRCurve(thresholds=dist[last], precision=precision, recall=recall, n_positive=n_pos)


@dataclass
class RejectionCurve:
    """Unseen-place rejection as the top-1 distance threshold grows.

    At threshold t, `rejection` is the fraction of queries with no true match whose
    top-1 distance is > t (correctly refused as new places); `recall` is the fraction
    of queries with a true match whose top-1 is within t and correct.
    """

    thresholds: np.ndarray
    rejection: np.ndarray
    recall: np.ndarray
    n_unseen: int
    n_seen: int


def rejection_curve(
    top1_distance: np.ndarray, top1_correct: np.ndarray, has_true: np.ndarray
) -> RejectionCurve:
    """The unseen-place rejection curve (see `RejectionCurve`), thresholds as `precision_recall`."""
    dist = np.asarray(top1_distance, dtype=np.float64)
    correct = np.asarray(top1_correct, dtype=bool)
    has_true = np.asarray(has_true, dtype=bool)
    thresholds = np.unique(dist[np.isfinite(dist)])
    unseen = np.sort(np.where(np.isfinite(dist[~has_true]), dist[~has_true], np.inf))
    seen_ok = np.sort(dist[has_true & correct & np.isfinite(dist)])
    n_unseen, n_seen = int((~has_true).sum()), int(has_true.sum())
    accepted_unseen = np.searchsorted(unseen, thresholds, side="right")
    accepted_seen = np.searchsorted(seen_ok, thresholds, side="right")
    rejection = 1.0 - accepted_unseen / n_unseen if n_unseen else np.full(thresholds.shape, np.nan)
    recall = accepted_seen / n_seen if n_seen else np.full(thresholds.shape, np.nan)
    return RejectionCurve(thresholds, rejection, recall, n_unseen, n_seen)


@dataclass
class Evaluation:
    """Everything one evaluation run measured: the figures for metrics.json and the curves."""

    metrics: dict[str, object]
    pr: PRCurve
    rejection: RejectionCurve | None
    recall_curve: np.ndarray  # recall@1..K, empty for the loop protocol
    yaw_errors: np.ndarray  # absolute errors of the correct top-1 matches


def _nan_to_none(value: float) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def confidence_metrics(
    confidence: np.ndarray | None, correct: np.ndarray, has_true: np.ndarray
) -> dict[str, float | None]:
    """F1max and recall at 100 % precision over the top 1's confidence (highest first;
    a query without one is never accepted); empty where there is none."""
    if confidence is None or not np.isfinite(np.asarray(confidence, np.float64)).any():
        return {}
    c = np.asarray(confidence, np.float64)
    pr = precision_recall(np.where(np.isfinite(c), -c, np.inf), correct, has_true)
    return {
        "f1_max_by_confidence": _nan_to_none(pr.f1_max),
        "recall@100%precision_by_confidence": _nan_to_none(pr.recall_at_full_precision),
    }


def retrieval_evaluation(
    retrieved: np.ndarray,
    distances: np.ndarray,
    truth: np.ndarray,
    yaw_est_top1: np.ndarray | None = None,
    yaw_true_top1: np.ndarray | None = None,
    confidence_top1: np.ndarray | None = None,
) -> Evaluation:
    """The multi-session protocol: queries against a database of another session.

    `retrieved` [Q, K] database indices (-1 for none), `distances` [Q, K] their
    distances, `truth` [Q, M] from `within_radius`; yaw arrays [Q] for the top-1
    (degrees, the estimate and the ground truth). K must reach recall@1%'s depth.
    `confidence_top1` [Q] (NaN: none) adds the precision-recall figures over it.
    """
    retrieved = np.asarray(retrieved, np.int64)
    distances = np.asarray(distances, np.float64)
    truth = np.asarray(truth, bool)
    db_size = truth.shape[1]
    correct = retrieval_correct(retrieved, truth)
    has_true = truth.any(axis=1)
    top1_dist = (
        np.where(retrieved[:, 0] >= 0, distances[:, 0], np.nan) if retrieved.size else np.zeros(0)
    )
    top1_ok = correct[:, 0] if correct.size else np.zeros(len(truth), bool)
    recalls = recall_at_n(correct, has_true)
    n1 = one_percent_n(db_size)
    r1pct = recall_at_one_percent(correct, has_true, db_size) if correct.shape[1] >= n1 else np.nan
    pr = precision_recall(top1_dist, top1_ok, has_true)
    rej = rejection_curve(top1_dist, top1_ok, has_true)
    yaw_err = np.array([])
    if yaw_est_top1 is not None and yaw_true_top1 is not None:
        ok = top1_ok & np.isfinite(np.asarray(yaw_est_top1, np.float64))
        yaw_err = yaw_errors_deg(np.asarray(yaw_est_top1)[ok], np.asarray(yaw_true_top1)[ok])
    metrics: dict[str, object] = {
        "protocol": "multi-session",
        "recall@1": _nan_to_none(recalls[0]) if recalls.size else None,
        "recall@1%": _nan_to_none(r1pct),
        "recall@N": [_nan_to_none(r) for r in recalls],
        "auc": _nan_to_none(pr.auc),
        "f1_max": _nan_to_none(pr.f1_max),
        "f1_max_threshold": _nan_to_none(pr.f1_max_threshold),
        "recall@100%precision": _nan_to_none(pr.recall_at_full_precision),
        **confidence_metrics(confidence_top1, top1_ok, has_true),
        **{k: _nan_to_none(v) for k, v in yaw_error_stats(yaw_err).items()},
        "num_queries": int(len(truth)),
        "num_queries_with_match": int(has_true.sum()),
        "num_queries_without_match": int((~has_true).sum()),
        "num_database": int(db_size),
        "num_correct_top1": int((top1_ok & has_true).sum()),
        "num_yaw_errors": int(yaw_err.size),
        # Gross yaw failures (a turned-around street): issue 24 asks for none.
        "num_yaw_errors_over_10deg": int((yaw_err > 10.0).sum()),
        "topk": int(correct.shape[1]),
        "one_percent_n": int(n1),
    }
    return Evaluation(metrics, pr, rej if rej.n_unseen else None, recalls, yaw_err)


def loop_evaluation(
    top1_distance: np.ndarray,
    top1_correct: np.ndarray,
    has_true: np.ndarray,
    yaw_est_top1: np.ndarray | None = None,
    yaw_true_top1: np.ndarray | None = None,
    confidence_top1: np.ndarray | None = None,
) -> Evaluation:
    """The single-sequence loop-closure protocol: one top-1 per scan among earlier scans
    (`confidence_top1`: as in `retrieval_evaluation`)."""
    dist = np.asarray(top1_distance, np.float64)
    ok = np.asarray(top1_correct, bool)
    has_true = np.asarray(has_true, bool)
    pr = precision_recall(dist, ok, has_true)
    yaw_err = np.array([])
    if yaw_est_top1 is not None and yaw_true_top1 is not None:
        good = ok & np.isfinite(np.asarray(yaw_est_top1, np.float64))
        yaw_err = yaw_errors_deg(np.asarray(yaw_est_top1)[good], np.asarray(yaw_true_top1)[good])
    n_pos = int(has_true.sum())
    metrics: dict[str, object] = {
        "protocol": "loop-closure",
        "recall@1": _nan_to_none(float((ok & has_true).sum()) / n_pos) if n_pos else None,
        "auc": _nan_to_none(pr.auc),
        "f1_max": _nan_to_none(pr.f1_max),
        "f1_max_threshold": _nan_to_none(pr.f1_max_threshold),
        "recall@100%precision": _nan_to_none(pr.recall_at_full_precision),
        **confidence_metrics(confidence_top1, ok, has_true),
        **{k: _nan_to_none(v) for k, v in yaw_error_stats(yaw_err).items()},
        "num_queries": int(len(dist)),
        "num_queries_with_match": n_pos,
        "num_queries_without_match": int((~has_true).sum()),
        "num_correct_top1": int((ok & has_true).sum()),
        "num_yaw_errors": int(yaw_err.size),
        # Gross yaw failures (a turned-around street): issue 24 asks for none.
        "num_yaw_errors_over_10deg": int((yaw_err > 10.0).sum()),
    }
    return Evaluation(metrics, pr, None, np.array([]), yaw_err)
