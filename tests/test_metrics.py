"""Evaluation metrics against cases worked out by hand and against naive loops."""

from __future__ import annotations

import numpy as np
import pytest

from disco_cli.evaluation import metrics as m

# --- the five-query example ------------------------------------------------------------------
# A database of 200 places; queries q0..q3 each have exactly one true match (places 0..3),
# q4 is a new place with none. Each query gets its top 3 (place index, distance):
#   q0: 0 1 2   top-1 distance 0.1   top-1 right
#   q1: 2 1 0   top-1 distance 0.2   top-1 wrong, right at rank 2
#   q2: 2 0 1   top-1 distance 0.4   top-1 right
#   q3: 0 1 2   top-1 distance 0.3   never right
#   q4: 1 0 2   top-1 distance 0.5   no true match: a false positive whenever accepted
# Recall@N over the 4 queries with a match: @1 = {q0, q2} = 2/4, @2 = @3 = {q0, q1, q2} = 3/4.
# Recall@1%: 1 % of 200 = 2, so recall@2 = 3/4.
# PR over the top-1 distance, thresholds ascending (TP, FP -> precision, recall = TP/4):
#   0.1: q0 TP        (1, 0) -> 1,   1/4     F1 = 2*1*.25/1.25  = 0.4
#   0.2: + q1 FP      (1, 1) -> 1/2, 1/4     F1 = 1/3
#   0.3: + q3 FP      (1, 2) -> 1/3, 1/4     F1 = 2/7
#   0.4: + q2 TP      (2, 2) -> 1/2, 1/2     F1 = 1/2
#   0.5: + q4 FP      (2, 3) -> 2/5, 1/2     F1 = 2*.4*.5/.9 = 4/9
# AUC (step-wise) = 1/4 * 1 + 1/4 * 1/2 = 0.375; F1max = 0.5 at threshold 0.4;
# recall at 100 % precision = 1/4.
# Rejection of the unseen q4 (distance 0.5): 1, 1, 1, 1, 0; seen recall 1/4, 1/4, 1/4, 1/2, 1/2.


def five_queries():
    truth = np.zeros((5, 200), dtype=bool)
    for q in range(4):
        truth[q, q] = True
    retrieved = np.array([[0, 1, 2], [2, 1, 0], [2, 0, 1], [0, 1, 2], [1, 0, 2]])
    top1 = np.array([0.1, 0.2, 0.4, 0.3, 0.5])
    distances = top1[:, None] + np.array([0.0, 0.05, 0.1])
    return retrieved, distances, truth


def test_five_query_example_by_hand():
    retrieved, distances, truth = five_queries()
    correct = m.retrieval_correct(retrieved, truth)
    has_true = truth.any(axis=1)
    np.testing.assert_allclose(m.recall_at_n(correct, has_true), [0.5, 0.75, 0.75])
    assert m.one_percent_n(200) == 2
    assert m.recall_at_one_percent(correct, has_true, 200) == pytest.approx(0.75)

    pr = m.precision_recall(distances[:, 0], correct[:, 0], has_true)
    np.testing.assert_allclose(pr.thresholds, [0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(pr.precision, [1, 1 / 2, 1 / 3, 1 / 2, 2 / 5])
    np.testing.assert_allclose(pr.recall, [1 / 4, 1 / 4, 1 / 4, 1 / 2, 1 / 2])
    assert pr.auc == pytest.approx(0.375)
    assert pr.f1_max == pytest.approx(0.5)
    assert pr.f1_max_threshold == pytest.approx(0.4)
    assert pr.recall_at_full_precision == pytest.approx(0.25)

    rej = m.rejection_curve(distances[:, 0], correct[:, 0], has_true)
    np.testing.assert_allclose(rej.rejection, [1, 1, 1, 1, 0])
    np.testing.assert_allclose(rej.recall, [1 / 4, 1 / 4, 1 / 4, 1 / 2, 1 / 2])
    assert (rej.n_unseen, rej.n_seen) == (1, 4)


def test_retrieval_evaluation_figures_match_the_hand_example():
    retrieved, distances, truth = five_queries()
    # Yaw of the correct top-1s (q0, q2): errors 2 and 4 degrees across the +-180 seam for q2.
    yaw_est = np.array([10.0, 50.0, 178.0, 0.0, 0.0])
    yaw_true = np.array([8.0, -90.0, -178.0, 30.0, 0.0])
    ev = m.retrieval_evaluation(retrieved, distances, truth, yaw_est, yaw_true)
    got = ev.metrics
    assert got["recall@1"] == pytest.approx(0.5)
    assert got["recall@1%"] == pytest.approx(0.75)
    assert got["recall@N"] == pytest.approx([0.5, 0.75, 0.75])
    assert got["auc"] == pytest.approx(0.375)
    assert got["f1_max"] == pytest.approx(0.5)
    assert got["yaw_err_mean_deg"] == pytest.approx(3.0)
    assert got["yaw_err_std_deg"] == pytest.approx(1.0)
    assert got["yaw_err_median_deg"] == pytest.approx(3.0)
    assert (got["num_queries"], got["num_queries_with_match"], got["num_database"]) == (5, 4, 200)
    assert got["num_correct_top1"] == 2


def test_missing_results_count_as_misses_and_are_never_accepted():
    truth = np.array([[True, False], [False, True]])
    retrieved = np.array([[0], [-1]])  # the second query got nothing back
    distances = np.array([[0.3], [np.nan]])
    ev = m.retrieval_evaluation(retrieved, distances, truth)
    assert ev.metrics["recall@1"] == pytest.approx(0.5)
    np.testing.assert_allclose(ev.pr.precision, [1.0])
    np.testing.assert_allclose(ev.pr.recall, [0.5])


def test_tied_distances_enter_together():
    # Two queries at the same distance, one right one wrong: one point at P = 1/2, R = 1/2.
    pr = m.precision_recall(np.array([0.2, 0.2]), np.array([True, False]), np.array([True, True]))
    np.testing.assert_allclose(pr.thresholds, [0.2])
    np.testing.assert_allclose(pr.precision, [0.5])
    np.testing.assert_allclose(pr.recall, [0.5])
    assert pr.recall_at_full_precision == 0.0


def naive_pr(dist, correct, has_true):
    """Reference: re-count TP and FP from scratch at every threshold."""
    ts = np.unique(dist)
    prec, rec = [], []
    for t in ts:
        acc = dist <= t
        tp = np.sum(acc & correct)
        fp = np.sum(acc & ~correct)
        prec.append(tp / (tp + fp))
        rec.append(tp / has_true.sum())
    return ts, np.array(prec), np.array(rec)


@pytest.mark.parametrize("seed", range(5))
def test_pr_curve_matches_a_naive_count(seed):
    rng = np.random.default_rng(seed)
    n = 60
    has_true = rng.random(n) < 0.7
    correct = has_true & (rng.random(n) < 0.6)
    dist = np.round(rng.random(n), 1)  # coarse, so that ties occur
    ts, prec, rec = naive_pr(dist, correct, has_true)
    pr = m.precision_recall(dist, correct, has_true)
    np.testing.assert_allclose(pr.thresholds, ts)
    np.testing.assert_allclose(pr.precision, prec)
    np.testing.assert_allclose(pr.recall, rec)
    auc = sum((rec[k] - (rec[k - 1] if k else 0.0)) * prec[k] for k in range(len(ts)))
    assert pr.auc == pytest.approx(auc)
    f1 = [2 * p * r / (p + r) if p + r else 0.0 for p, r in zip(prec, rec)]
    assert pr.f1_max == pytest.approx(max(f1))


def test_perfect_ranking_has_auc_one():
    right = np.array([True, True, False])
    pr = m.precision_recall(np.array([0.1, 0.2, 0.9]), right, right)
    assert pr.auc == pytest.approx(1.0)
    assert pr.f1_max == pytest.approx(1.0)
    assert pr.recall_at_full_precision == pytest.approx(1.0)


def test_yaw_wraps_at_180():
    wrapped = m.wrap_deg([190.0, -190.0, 180.0, -180.0, 540.0, 0.0])
    np.testing.assert_allclose(wrapped, [-170, 170, 180, 180, 180, 0])
    errors = m.yaw_errors_deg([179.0, -170.0, 180.0, 90.0], [-179.0, 170.0, -180.0, -90.0])
    np.testing.assert_allclose(errors, [2, 20, 0, 180])


def test_yaw_stats_empty_is_nan():
    stats = m.yaw_error_stats(np.array([]))
    assert all(np.isnan(v) for v in stats.values())


def test_within_radius_matches_a_loop():
    rng = np.random.default_rng(3)
    q, d = rng.random((7, 2)) * 10, rng.random((11, 2)) * 10
    want = np.array([[np.hypot(*(a - b)) <= 3.0 for b in d] for a in q])
    np.testing.assert_array_equal(m.within_radius(q, d, 3.0), want)


def test_loop_evaluation_counts():
    dist = np.array([0.1, 0.2, 0.3, 0.4])
    correct = np.array([True, False, True, False])
    has_true = np.array([True, True, True, False])
    ev = m.loop_evaluation(dist, correct, has_true)
    # 0.1 TP (1, 1/3), 0.2 FP (1/2, 1/3), 0.3 TP (2/3, 2/3), 0.4 FP (1/2, 2/3)
    assert ev.metrics["recall@1"] == pytest.approx(2 / 3)
    assert ev.metrics["auc"] == pytest.approx(1 / 3 + 1 / 3 * 2 / 3)
    assert ev.metrics["f1_max"] == pytest.approx(2 / 3)
    assert ev.metrics["recall@100%precision"] == pytest.approx(1 / 3)
