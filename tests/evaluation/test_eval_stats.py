"""Bootstrap intervals and paired differences (precond/evaluation/stats.py): pure functions, seeded."""

from __future__ import annotations

import pytest

from precond.evaluation.stats import bootstrap, paired_difference


def test_constant_values_have_a_zero_width_interval() -> None:
    interval = bootstrap([[1.0, 1.0], [1.0], [1.0, 1.0, 1.0]])
    assert (interval.estimate, interval.low, interval.high, interval.n) == (1.0, 1.0, 1.0, 6)


def test_the_estimate_pools_all_values_and_the_interval_brackets_it() -> None:
    units = [[1.0, 0.0, 1.0], [0.0], [1.0, 1.0], [0.0, 0.0, 1.0, 1.0]]
    interval = bootstrap(units, seed=3)
    assert interval.estimate == pytest.approx(6 / 10)
    assert interval.low < interval.estimate < interval.high
    assert bootstrap(units, seed=3) == interval  # seeded: the same interval every time


def test_more_units_give_a_narrower_interval() -> None:
    few = bootstrap([[1.0], [0.0]] * 5)
    many = bootstrap([[1.0], [0.0]] * 200)
    assert many.high - many.low < few.high - few.low


def test_no_values_no_interval() -> None:
    assert bootstrap([]).n == 0 and bootstrap([[], []]).estimate == 0.0


def test_a_constant_gain_on_every_unit_is_certain_however_noisy_the_units() -> None:
    a = {f"d{k}": [k / 20, (k % 3) / 3] for k in range(20)}
    b = {key: [v + 0.1 for v in values] for key, values in a.items()}
    diff = paired_difference(a, b)
    assert diff.estimate == pytest.approx(0.1)
    assert diff.low == pytest.approx(0.1) and diff.high == pytest.approx(0.1)
    assert diff.excludes_zero()


def test_identical_configurations_differ_by_nothing() -> None:
    a = {"x": [0.2, 0.9], "y": [0.5], "z": [1.0, 0.0]}
    diff = paired_difference(a, dict(a))
    assert (diff.estimate, diff.low, diff.high) == (0.0, 0.0, 0.0) and not diff.excludes_zero()


def test_a_difference_that_goes_both_ways_includes_zero() -> None:
    a = {f"d{k}": [1.0 if k % 2 else 0.0] for k in range(30)}
    b = {f"d{k}": [0.0 if k % 2 else 1.0] for k in range(30)}
    diff = paired_difference(a, b)
    assert diff.low < 0 < diff.high and not diff.excludes_zero()


def test_pairs_only_the_units_both_sides_measured() -> None:
    a = {"x": [0.0], "y": [0.0], "only-a": [1.0]}
    b = {"x": [1.0], "y": [1.0], "only-b": [0.0]}
    diff = paired_difference(a, b)
    assert diff.estimate == 1.0 and diff.n == 2
