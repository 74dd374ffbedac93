"""The top-level warnings of an inference: every action whose rule is empty or not backed by the demonstrations.

An empty rule means "every call allowed", and a rule from one or two calls is a guess; the answer's rules look the
same either way, so each such action gets a warning saying which case it is and why (the README: nothing is
silent). One function per case, tried in order; the first that applies words the action's warning, so a new
case (a rule that rests on assumptions) is one more function in `CASES`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from engine.evidence import MIN_DIALOGS, MIN_OCCURRENCES, too_few
from sandbox.types import Point


@dataclass(frozen=True)
class Outcome:
    """What an inference decided for one action, and what it had to decide from."""

    action: str
    occurrences: Sequence[Point]
    rules: Sequence[str]
    model: bool
    """The code model proposed rules (so a rule without evidence is its zero-shot guess)."""
    tolerance: float
    """Evidence weighting on (> 0): too few calls are treated as none; off: a rule may rest on them."""


def _consequence(outcome: Outcome) -> str:
    if not outcome.rules:
        return "no rule could be learned for it, so its rule is empty: every call of it is allowed"
    if outcome.occurrences and outcome.tolerance <= 0:
        return "its rule holds at those few calls, which cannot tell a requirement from a coincidence"
    if outcome.model:
        return ("its rule is the code model's zero-shot guess from the spec (kept only when several samples "
                "agree), not learned from demonstrations")
    return "its rule is not learned from demonstrations"


def never_demonstrated(outcome: Outcome) -> str | None:
    if outcome.occurrences:
        return None
    return f"no occurrence: no demonstration calls {outcome.action}; {_consequence(outcome)}"


def thinly_demonstrated(outcome: Outcome) -> str | None:
    if not too_few(outcome.occurrences):
        return None
    calls = len(set(outcome.occurrences))
    dialogs = len({p.demo for p in outcome.occurrences})
    return (f"thin evidence: {outcome.action} is called {calls} time(s) in {dialogs} demonstration(s); learning a "
            f"rule takes at least {MIN_OCCURRENCES} calls in {MIN_DIALOGS} demonstrations (fewer could be "
            f"coincidence); {_consequence(outcome)}")


def nothing_kept(outcome: Outcome) -> str | None:
    if outcome.rules:
        return None
    return (f"empty rule: no candidate condition for {outcome.action} passed validation at its "
            f"{len(set(outcome.occurrences))} demonstrated calls, so every call of it is allowed (the candidates "
            "say why each was dropped)")


CASES: tuple[Callable[[Outcome], str | None], ...] = (never_demonstrated, thinly_demonstrated, nothing_kept)


def rule_warnings(
    actions: Sequence[str],
    occurrences: Mapping[str, Sequence[Point]],
    preconditions: Mapping[str, Sequence[str]],
    model: bool,
    tolerance: float,
) -> dict[str, str]:
    """Per action whose rule is empty or not learned from enough demonstrated calls, why; others are absent."""
    warnings: dict[str, str] = {}
    for action in actions:
        outcome = Outcome(action, occurrences.get(action, ()), preconditions.get(action, ()), model, tolerance)
        for case in CASES:
            if (warning := case(outcome)) is not None:
                warnings[action] = warning
                break
    return warnings
