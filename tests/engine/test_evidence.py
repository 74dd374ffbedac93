"""The statistics of evidence-weighted validation (precond/engine/judging/evidence.py), on counts alone."""

from __future__ import annotations

import math

import pytest

from precond.engine.judging.evidence import (
    CHANCE_ALPHA,
    MIN_DIALOGS,
    MIN_OCCURRENCES,
    STRONG_ALPHA,
    Evidence,
    OccurrenceIndex,
    binomial_tail,
    gather,
    strongly_separated,
    thin,
    verdict,
    wilson_lower,
)
from precond.sandbox.types import Point, PointGrid


def test_binomial_tail_matches_the_exact_sum() -> None:
    for n, k, p in [(10, 3, 0.2), (25, 25, 0.9), (40, 1, 0.05), (7, 0, 0.5), (3, 4, 0.5), (200, 190, 0.97)]:
        exact = sum(math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k, n + 1))
        assert binomial_tail(n, k, p) == pytest.approx(exact, rel=1e-9, abs=1e-12)
    assert binomial_tail(5, 1, 0.0) == 0.0 and binomial_tail(5, 5, 1.0) == 1.0


def test_confidence_grows_with_the_evidence() -> None:
    assert wilson_lower(1, 1) == pytest.approx(0.27, abs=0.01)
    assert wilson_lower(10, 10) == pytest.approx(0.79, abs=0.01)
    assert wilson_lower(40, 40) == pytest.approx(0.94, abs=0.01)
    assert wilson_lower(0, 0) == 0.0 and wilson_lower(39, 40) < wilson_lower(40, 40)


def _evidence(n: int, holds: int, elsewhere: int = 1000, holds_elsewhere: int = 200) -> Evidence:
    return Evidence(n, holds, elsewhere, holds_elsewhere)


def test_a_single_slip_does_not_kill_a_true_rule() -> None:
    assert verdict(_evidence(25, 24), 0.05) == "tolerated"
    assert verdict(_evidence(25, 25), 0.05) == "held"


def test_more_exceptions_than_the_tolerance_refute_a_weakly_separated_rule() -> None:
    # holds at 60% of the other points: 22 of 25 at the calls is likely enough (p ~ 0.01) to be a correlation
    assert verdict(_evidence(25, 22, holds_elsewhere=600), 0.05) == "refuted"  # 3 of 25 = 12% > 5%
    assert verdict(_evidence(10, 9, holds_elsewhere=600), 0.05) == "refuted"  # 1 of 10 = 10% > 5%
    assert verdict(_evidence(10, 9, holds_elsewhere=600), 0.1) == "tolerated"


def test_a_true_rule_with_15_percent_slips_is_kept_when_it_separates_strongly() -> None:
    # `not informed_slot[slot]` for REQUEST with re-asked slots: 34 of 40 calls, 30% of the other points
    slipped = _evidence(40, 34, holds_elsewhere=300)
    assert slipped.chance() < STRONG_ALPHA and strongly_separated(slipped)
    assert verdict(slipped, 0.05) == "tolerated"


def test_strong_separation_forgives_only_a_minority_of_the_calls_and_only_with_enough_of_them() -> None:
    assert verdict(_evidence(40, 26, holds_elsewhere=100), 0.05) == "refuted"  # 35% exceptions: not slips
    # a rare condition (6% of the points) at 3 of 4 or 4 of 5 calls: strong by the tail, but one exception in
    # four or five calls cannot be told from a rule that fails in some situations (REQ_MORE: `user.no_more`)
    for n in (4, 5):
        coincidence = _evidence(n, n - 1, holds_elsewhere=60)
        assert coincidence.chance() < STRONG_ALPHA and verdict(coincidence, 0.05) == "refuted"
    assert verdict(_evidence(4, 4, holds_elsewhere=60), 0.05) == "held"


def test_strong_separation_is_off_under_strict_validation() -> None:
    assert verdict(_evidence(40, 34, holds_elsewhere=300), 0.0) == "refuted"


def test_tolerance_zero_is_strict_validation_and_nothing_else() -> None:
    assert verdict(_evidence(25, 24), 0.0) == "refuted"
    assert verdict(_evidence(1, 1), 0.0) == "held"  # no thin rule, no chance test: the paper's behaviour
    assert verdict(_evidence(10, 10, holds_elsewhere=990), 0.0) == "held"
    assert not thin(_calls(1), 0.0)


def _calls(n: int, dialogs: int | None = None) -> list[Point]:
    """n calls spread over `dialogs` demonstrations (default: one call per demonstration)."""
    return [Point(demo=i % (dialogs or n), position=i, args=()) for i in range(n)]


def test_a_coincidence_at_one_or_two_occurrences_is_not_a_rule() -> None:
    for n in range(1, MIN_OCCURRENCES):
        assert verdict(_evidence(n, n, holds_elsewhere=1), 0.05) == "thin"
        assert thin(_calls(n), 0.05)
    assert not thin([], 0.05)  # never demonstrated is its own case (zero-shot), not thin
    assert not thin(_calls(MIN_OCCURRENCES), 0.05)


def test_calls_from_too_few_dialogs_are_thin_however_many() -> None:
    """Seven failure notices in two dialogs are two situations, not seven: what held there (`query_success is
    not None`) is a coincidence of those dialogs as much as a single call's would be."""
    assert thin(_calls(7, dialogs=MIN_DIALOGS - 1), 0.05)
    assert not thin(_calls(7, dialogs=MIN_DIALOGS), 0.05)
    assert not thin(_calls(7, dialogs=1), 0.0)  # strict validation: the paper's behaviour, no thin rule


def test_a_condition_true_almost_everywhere_says_nothing() -> None:
    common = _evidence(10, 10, holds_elsewhere=950)
    assert common.chance() >= CHANCE_ALPHA and verdict(common, 0.05) == "chance"
    rare = _evidence(10, 10, holds_elsewhere=100)
    assert rare.chance() < 1e-6 and verdict(rare, 0.05) == "held"


def test_gather_counts_occurrences_exceptions_and_other_points() -> None:
    grid = PointGrid([(0, p) for p in range(6)], [("a",), ("b",)])  # 12 points
    occurrences = [Point(0, 1, ("a",)), Point(0, 3, ("b",)), Point(0, 5, ("a",))]
    index = OccurrenceIndex.of(grid, occurrences)
    satisfied = sum(1 << grid.index(p) for p in (occurrences[0], occurrences[2], Point(0, 2, ("a",))))
    e = gather(satisfied, index)
    assert (e.occurrences, e.holds, e.elsewhere, e.holds_elsewhere) == (3, 2, 9, 1)
    assert e.exceptions == (occurrences[1],)
    assert gather(satisfied | 1 << grid.index(occurrences[1]), index).exceptions == ()
