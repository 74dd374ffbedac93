"""The paper's scores: precondition P/R/F1 over satisfaction sets, and the policy's turn-level F1.

Precondition inference (paper, eq. prec_rec). For an action a, C_a is the set of points
(test trajectory, position, argument tuple) at which a's precondition holds on the state before that
position; a point is a bit in a bitset, so sets are Python ints and intersections are `&`.

    precision = |C_pred ∩ C_gt| / |C_pred|      recall = |C_pred ∩ C_gt| / |C_gt|

Edge cases, chosen so that a score never rewards saying nothing and never divides by zero:

* |C_pred| = 0 (the prediction never allows the action): precision is 1.0 (no false positive was made),
  recall is 0.0 unless |C_gt| = 0 as well. F1 is then 0.0, so "never allowed" cannot look good.
* |C_gt| = 0 (the ground truth never allows the action on the test points): recall is 1.0 (nothing to find),
  precision is 0.0 unless the prediction is empty too. Both empty: P = R = F1 = 1.0 (perfect agreement).
* F1 = 0.0 when P + R = 0.
* An action with no points at all (an argument-taking action without any argument value) has no score; it is
  reported as unscored and left out of the macro average rather than counted as 1.0 or 0.0.
* Evaluating a precondition that raises (KeyError, TypeError, a failing call, or no instance of the class
  yet at that position) counts as "not satisfied" at that point: the action would be refused there. The
  sandbox implements this; `tests/evaluation` checks it end to end.

Macro averages are unweighted means over the scored actions of one domain; a benchmark with several domains
(SGD) is the unweighted mean of its domains' macros, so a domain with more actions does not dominate.

Policy (paper, "Precondition-aware Agent Policy"): per system turn, predicted and reference actions are
compared as multisets of calls; the turn's F1 is averaged over turns. A turn where both are empty scores 1.0.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class PRF:
    precision: float
    recall: float
    f1: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class ActionScore:
    """One action's sets summarised; sizes are kept so that reports can show why a score is low."""

    action: str
    n_points: int
    n_pred: int
    n_gt: int
    n_both: int
    prf: PRF | None  # None: no points, unscored


def f1_of(precision: float, recall: float) -> float:
    total = precision + recall
    return 0.0 if total == 0 else 2 * precision * recall / total


def prf_from_counts(n_pred: int, n_gt: int, n_both: int) -> PRF:
    precision = 1.0 if n_pred == 0 else n_both / n_pred
    recall = 1.0 if n_gt == 0 else n_both / n_gt
    if n_pred == 0 and n_gt > 0:
        recall = 0.0
    if n_gt == 0 and n_pred > 0:
        precision = 0.0
    return PRF(precision, recall, f1_of(precision, recall))


def score_action(action: str, n_points: int, predicted: int, truth: int) -> ActionScore:
    """`predicted` and `truth` are bitsets over the action's points."""
    n_pred, n_gt, n_both = predicted.bit_count(), truth.bit_count(), (predicted & truth).bit_count()
    prf = prf_from_counts(n_pred, n_gt, n_both) if n_points else None
    return ActionScore(action, n_points, n_pred, n_gt, n_both, prf)


def macro(scores: Iterable[PRF | None]) -> PRF:
    """Unweighted mean of P, R and F1 over the scored entries (F1 is averaged, not recomputed)."""
    scored = [s for s in scores if s is not None]
    if not scored:
        return PRF(0.0, 0.0, 0.0)
    n = len(scored)
    return PRF(sum(s.precision for s in scored) / n, sum(s.recall for s in scored) / n,
               sum(s.f1 for s in scored) / n)


def turn_f1(predicted: Sequence[str], reference: Sequence[str]) -> PRF:
    """Multiset P/R/F1 of one turn: a call predicted twice but said once counts once."""
    if not predicted and not reference:
        return PRF(1.0, 1.0, 1.0)
    both = sum((Counter(predicted) & Counter(reference)).values())
    precision = both / len(predicted) if predicted else 0.0
    recall = both / len(reference) if reference else 0.0
    return PRF(precision, recall, f1_of(precision, recall))


def mean(values: Iterable[float]) -> float:
    items = list(values)
    return sum(items) / len(items) if items else 0.0


def percentile(values: Sequence[float], q: float) -> float:
    """Nearest-rank percentile; enough for latency tables on a few hundred samples."""
    if not values:
        return 0.0
    ordered = sorted(values)
    rank = min(len(ordered), max(1, math.ceil(q / 100 * len(ordered))))
    return ordered[rank - 1]


def domain_macro(per_action: Mapping[str, ActionScore]) -> PRF:
    return macro(s.prf for s in per_action.values())
