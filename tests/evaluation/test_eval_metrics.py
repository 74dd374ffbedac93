"""Metric edge cases (documented in precond/evaluation/metrics.py) and the policy's turn F1."""

from __future__ import annotations

import pytest

from precond.evaluation.metrics import PRF, macro, percentile, prf_from_counts, score_action, turn_f1


def test_exact_prediction_scores_one() -> None:
    assert prf_from_counts(n_pred=5, n_gt=5, n_both=5) == PRF(1.0, 1.0, 1.0)


def test_empty_prediction_has_precision_one_but_no_recall() -> None:
    assert prf_from_counts(n_pred=0, n_gt=4, n_both=0) == PRF(1.0, 0.0, 0.0)


def test_empty_ground_truth_has_recall_one_but_no_precision() -> None:
    assert prf_from_counts(n_pred=3, n_gt=0, n_both=0) == PRF(0.0, 1.0, 0.0)


def test_both_empty_is_perfect_agreement() -> None:
    assert prf_from_counts(n_pred=0, n_gt=0, n_both=0) == PRF(1.0, 1.0, 1.0)


def test_always_allowed_has_full_recall_and_base_rate_precision() -> None:
    everything, truth = 0b1111, 0b0011
    score = score_action("A.a", 4, everything, truth)
    assert score.prf == PRF(0.5, 1.0, pytest.approx(2 / 3))


def test_action_without_points_is_unscored_and_left_out_of_macro() -> None:
    unscored = score_action("A.a", 0, 0, 0)
    assert unscored.prf is None
    perfect = score_action("A.b", 2, 0b11, 0b11)
    assert macro([unscored.prf, perfect.prf]) == PRF(1.0, 1.0, 1.0)


def test_macro_averages_f1_rather_than_recomputing_it() -> None:
    assert macro([PRF(1.0, 0.0, 0.0), PRF(1.0, 1.0, 1.0)]) == PRF(1.0, 0.5, 0.5)


def test_turn_f1_compares_multisets() -> None:
    predicted = ["s.REQUEST('city')", "s.REQUEST('city')", "s.OFFER('name')"]
    reference = ["s.REQUEST('city')", "s.REQUEST('date')"]
    score = turn_f1(predicted, reference)
    assert (score.precision, score.recall) == (pytest.approx(1 / 3), 0.5)


def test_turn_f1_edge_cases() -> None:
    assert turn_f1([], []) == PRF(1.0, 1.0, 1.0)
    assert turn_f1([], ["x()"]) == PRF(0.0, 0.0, 0.0)
    assert turn_f1(["x()"], []) == PRF(0.0, 0.0, 0.0)


def test_percentile_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert percentile(values, 50) == 50.0
    assert percentile(values, 95) == 95.0
    assert percentile([], 50) == 0.0
