"""Conditions every other guarded action keeps, assumed for an action the demonstrations never show.

A never-demonstrated guarded action gets `options.unseen`'s placeholder: under 'refuse', every call is refused
until a rule exists. For a tool agent that refuses every first use of a write (a booking, a certificate) the
demonstrations happen not to show, although its policy usually asks of it what it asks of the agent's other
writes: the record it names was read, the user it names was looked up. Here such an action takes, instead of
the placeholder, the conditions

- chosen by at least MIN_SHARERS other guarded actions, and by every other guarded action that has the same
  text among its valid candidates (its parameters named alike): shared, never one action's quirk;
- among its own valid candidates, naming at least one of its parameters (a read of the key it names, not a
  fact of the conversation such as "the last call succeeded", which says nothing of this call's arguments);
- where labelled calls of it exist: holding at every call labelled 'allow' and failing at every call labelled
  'refuse' together, so that they neither refuse what the labels allow nor allow what they refuse.

Each is `assumed` (a human decides) and the action's warning names where it came from; with none adopted the
placeholder stays.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import replace

from precond.engine.judging.counterexamples import Outcome, Separation
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.programs import Method

MIN_SHARERS = 2
"""How many other guarded actions must keep a condition before an unseen action assumes it: one is a quirk."""


def assume_shared(chosen: dict[str, list[str]], ranked: dict[str, Ranked], separated: Mapping[str, Separation],
                  guarded: Sequence[str], methods: Mapping[str, Method]) -> None:
    """Replace, in `chosen` and `ranked`, each placeholder with the shared conditions (module docstring)."""
    for action in guarded:
        if chosen.get(action) != [UNSEEN_RULE]:
            continue
        params = _parameters(methods.get(action))
        own = {c.expression for c in ranked[action].valid}
        shared = [e for e in _shared(chosen, ranked, guarded, action) if e in own and _names(e) & params]
        separation = separated.get(action)
        outcome = separation.outcome if separation else None
        if not shared or (outcome is not None and not _fits_labels(shared, outcome)):
            continue
        chosen[action] = shared
        ranked[action] = replace(ranked[action], decided={e: "assumed" for e in shared}, assumed=(
            f"never demonstrated: assumed {len(shared)} condition(s) every other guarded action that can state "
            f"them keeps ({', '.join(shared)}) instead of refusing every call (options.unseen: 'refuse'); "
            f"review them, or write the rule"))


def _shared(chosen: Mapping[str, list[str]], ranked: Mapping[str, Ranked], guarded: Sequence[str],
            action: str) -> list[str]:
    """The rules kept by at least MIN_SHARERS other guarded actions and by every other one able to state them."""
    others = [b for b in guarded if b != action and chosen.get(b) and chosen[b] != [UNSEEN_RULE]]
    texts = sorted({e for b in others for e in chosen[b]})
    out = []
    for e in texts:
        able = [b for b in others if any(c.expression == e for c in ranked[b].valid) or e in chosen[b]]
        if len(able) >= MIN_SHARERS and all(e in chosen[b] for b in able):
            out.append(e)
    return out


def _fits_labels(shared: Sequence[str], outcome: Outcome) -> bool:
    """Whether the conditions together allow every labelled 'allow' call and refuse every labelled 'refuse' one."""
    if any(e not in outcome.truth for e in shared):
        return False
    both = ~0
    for e in shared:
        both &= outcome.truth[e]
    return not outcome.positive & ~both and not outcome.negative & both


def _parameters(method: Method | None) -> set[str]:
    """The names of a method's arguments, `self` left out."""
    if method is None:
        return set()
    return {*method.positional, *method.kwonly} - {"self"}


def _names(expression: str) -> set[str]:
    """The plain names an expression reads."""
    try:
        tree = ast.parse(expression, mode="eval")
    except SyntaxError:
        return set()
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
