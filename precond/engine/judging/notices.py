"""The top-level warnings of an inference: every action whose rule is empty or not backed by the demonstrations.

An empty rule means "every call allowed", and a rule from one or two calls is a guess; the answer's rules look the
same either way, so each such action gets a warning saying which case it is and why (docs/api.md: nothing is
silent). One function per case, tried in order; the first that applies words the action's warning, so a new
case (a rule that rests on assumptions) is one more function in `CASES`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from precond.engine.judging.evidence import MIN_DIALOGS, MIN_OCCURRENCES, strict, too_few
from precond.sandbox.types import Point
from precond_client.schemas import Decided, InferOptions

MAX_LISTED_ASSUMED = 8


@dataclass(frozen=True)
class Outcome:
    """What an inference decided for one action, and what it had to decide from."""

    action: str
    occurrences: Sequence[Point]
    rules: Sequence[str]
    model: bool
    """The code model proposed rules (so a rule without evidence is its zero-shot guess)."""
    options: InferOptions
    """The request's: with evidence weighting on (tolerance > 0) too few calls are treated as none, off a rule
    may rest on them; `unseen` says what an action without a rule gets."""
    decided: Mapping[str, Decided]
    """How each rule was decided (`established`, `assumed`, `zero-shot`, `unseen`)."""

    @property
    def assumed(self) -> list[str]:
        return [rule for rule in self.rules if self.decided.get(rule) == "assumed"]


def _consequence(outcome: Outcome) -> str:
    if not outcome.rules:
        allow = " (options.unseen: 'allow')" if not outcome.occurrences else ""
        return f"no rule could be learned for it, so its rule is empty: every call of it is allowed{allow}"
    if any(outcome.decided.get(rule) == "unseen" for rule in outcome.rules):
        return ("no prior rule applies and the code model kept no zero-shot guess, so every call of it is refused "
                "(options.unseen: 'refuse') until a rule is written or learned from demonstrations that show it")
    if any(outcome.decided.get(rule) == "transferred" for rule in outcome.rules):
        return "its rule is transferred from the prior rules (learned for other services; `evidence` names them)"
    if outcome.occurrences and strict(outcome.options.tolerance):
        return "its rule holds at those few calls, which cannot tell a requirement from a coincidence"
    if outcome.assumed:
        return f"its rules are assumed, the facts its few calls share: {_listed(outcome.assumed)}"
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


def rests_on_assumptions(outcome: Outcome) -> str | None:
    if not outcome.assumed:
        return None
    return (f"assumed: {len(outcome.assumed)} rule(s) of {outcome.action} could not be ruled out as requirements, "
            f"though the demonstrations cannot tell them from correlates (review them): {_listed(outcome.assumed)}")


def _listed(rules: Sequence[str]) -> str:
    more = "; ..." if len(rules) > MAX_LISTED_ASSUMED else ""
    return "; ".join(rules[:MAX_LISTED_ASSUMED]) + more


def nothing_kept(outcome: Outcome) -> str | None:
    if outcome.rules:
        return None
    return (f"empty rule: no candidate condition for {outcome.action} passed validation at its "
            f"{len(set(outcome.occurrences))} demonstrated calls, so every call of it is allowed (the candidates "
            "say why each was dropped)")


CASES: tuple[Callable[[Outcome], str | None], ...] = (
    never_demonstrated, thinly_demonstrated, rests_on_assumptions, nothing_kept)


def rule_warnings(
    actions: Sequence[str],
    occurrences: Mapping[str, Sequence[Point]],
    preconditions: Mapping[str, Sequence[str]],
    decided: Mapping[str, Mapping[str, Decided]],
    model: bool,
    options: InferOptions,
    dropped_priors: Mapping[str, Sequence[str]] | None = None,
) -> dict[str, str]:
    """Per action whose rule is empty, assumed or not learned from enough demonstrated calls, why, and the prior
    rules that did not apply to it (`engine.priors`); others are absent."""
    warnings: dict[str, str] = {}
    for action in actions:
        outcome = Outcome(action, occurrences.get(action, ()), preconditions.get(action, ()), model, options,
                          decided.get(action, {}))
        for case in CASES:
            if (warning := case(outcome)) is not None:
                warnings[action] = warning
                break
        if dropped := (dropped_priors or {}).get(action):
            listed = f"prior rules that do not apply here were dropped: {_listed(list(dropped))}"
            warnings[action] = f"{warnings[action]}; {listed}" if action in warnings else listed
    return warnings
