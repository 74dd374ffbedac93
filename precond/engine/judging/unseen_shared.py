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

Not where another guarded action toggles the state of an argument named like one of its own: when that action keeps
a condition on it (the box it opens is closed) that its own calls undo (after most of them the condition fails for
the same arguments before the action is called with them again: the box is open), this action may be the one that
undoes the effect (closing) and need the opposite, and nothing demonstrated says which way it goes. The shared
conditions alone would then allow it whatever that state is, so the placeholder stays, and the warning names the
toggled conditions. A condition other actions keep without undoing it (a policy's clause on the record a write
names) says nothing of the sort, and the shared conditions are assumed as above.

Each is `assumed` (a human decides) and the action's warning names where it came from; with none adopted the
placeholder stays.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from precond.engine.judging.counterexamples import Outcome, Separation
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.programs import Method
from precond.sandbox import Point

MIN_SHARERS = 2
"""How many other guarded actions must keep a condition before an unseen action assumes it: one is a quirk."""


@dataclass(frozen=True)
class Calls:
    """Where each action's conditions were judged (its points) and where it was called (its occurrences)."""

    points: Mapping[str, Sequence[Point]]
    occurrences: Mapping[str, Sequence[Point]]


def assume_shared(chosen: dict[str, list[str]], ranked: dict[str, Ranked], separated: Mapping[str, Separation],
                  guarded: Sequence[str], methods: Mapping[str, Method], calls: Calls) -> None:
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
        toggled = _toggled(chosen, ranked, guarded, action, params, calls)
        if toggled:
            ranked[action] = replace(ranked[action], assumed=(
                f"never demonstrated: the conditions the other guarded actions share ({', '.join(shared)}) are not "
                f"assumed, since another action's calls undo what it asks of the same arguments "
                f"({', '.join(toggled)}), and nothing shows whether this action needs it or its opposite"))
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


def _toggled(chosen: Mapping[str, list[str]], ranked: Mapping[str, Ranked], guarded: Sequence[str], action: str,
             params: set[str], calls: Calls) -> list[str]:
    """The conditions another guarded action keeps on an argument named like one of this action's and undoes by
    its own calls."""
    others = [b for b in guarded if b != action and chosen.get(b) and chosen[b] != [UNSEEN_RULE]]
    return sorted({e for b in others for e in chosen[b] if _names(e) & params and _undone(e, b, ranked[b], calls)})


def _undone(expression: str, action: str, ranked: Ranked, calls: Calls) -> bool:
    """Whether, after more than half of the action's calls, the condition fails at a later point of the same
    demonstration with the same arguments, before the action is called with them again."""
    result = next((r for r in ranked.results if r.expression == expression), None)
    occurrences = calls.occurrences.get(action, ())
    if result is None or not occurrences:
        return False
    later: dict[tuple[int, tuple[object, ...]], list[tuple[int, int]]] = defaultdict(list)
    for bit, point in enumerate(calls.points.get(action, ())):
        later[(point.demo, point.args)].append((point.position, bit))
    starts: dict[tuple[int, tuple[object, ...]], list[int]] = defaultdict(list)
    for occ in occurrences:
        starts[(occ.demo, occ.args)].append(occ.position)
    undone = 0
    for key, positions in starts.items():
        bounds = sorted(positions)
        for start, end in zip(bounds, [*bounds[1:], None], strict=True):
            undone += any(start < position and (end is None or position < end) and not result.satisfied >> bit & 1
                          for position, bit in later[key])
    return undone * 2 > len(occurrences)


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
