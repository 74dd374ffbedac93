"""Conditions one action's labels chose, adopted by another action whose calls to allow all meet them.

A policy states a condition once for several tools ("an order can only be cancelled or modified if its status is
'pending'"), but a request's labelled calls seldom show each of those tools broken in each way: the calls
labelled 'refuse' for breaking it may all be cancellations. `counterexamples.separate` learns, per action, only
what that action's own labelled calls show; here a condition it chose for one action from the labels (one that
refuses calls labelled 'refuse' there: `Outcome.from_labels`) becomes a rule of another action too, where

- the other action has it among its own judged conditions (the same text: its parameters named alike), and
- it holds at every call to allow of the other action (demonstrated, or labelled 'allow'),

so that it never refuses a call the other action's evidence allows. It is established by the labels of the
action it came from, and says so. At most the conditions the labels chose for the other actions (a handful an
action: `counterexamples.MAX_REQUIRED` required ones and the conditions of at most MAX_TERMS terms), each
checked against bits already computed: no judging, no search.
"""

from __future__ import annotations

from collections.abc import Mapping

from precond.engine.judging.counterexamples import Made, Outcome, Separation
from precond.engine.judging.evidence import OccurrenceIndex
from precond.engine.judging.report import Ranked


def shared(separated: Mapping[str, Separation], unlabelled: Mapping[str, tuple[Ranked, OccurrenceIndex]]
           ) -> dict[str, Separation]:
    """Each action's separation with the conditions other actions' labels chose that it adopts (module
    docstring); an action with nothing to adopt keeps its separation as it is. `unlabelled`: the actions with
    demonstrated calls and no labelled one, their ranking and demonstrated calls: they adopt too (a
    separation of their own made for it), where every demonstrated call meets the condition."""
    chosen = {a: s.outcome.from_labels for a, s in separated.items() if s.outcome}
    out = dict(separated)
    for action, separation in separated.items():
        outcome, made = separation.outcome, separation.made
        if outcome is None or made is None or not outcome.positive:
            continue
        have = {c.representative.expression for c in made.chosen}
        adopted = {e: other for other, texts in sorted(chosen.items()) if other != action for e in texts
                   if e not in have and e in outcome.truth and not outcome.positive & ~outcome.truth[e]}
        if adopted:
            _adopt(made, adopted)
            out[action] = made.separation(outcome, [], separation.exempt, separation.unshown)
    for action, (ranked, index) in unlabelled.items():
        satisfied = {r.expression: r.satisfied for r in ranked.results}
        have = {c.representative.expression for c in ranked.chosen}
        adopted = {e: other for other, texts in sorted(chosen.items()) for e in texts
                   if e not in have and e in satisfied and not index.mask & ~satisfied[e]}
        if adopted and index.mask and None not in index.bits:
            made = Made(ranked, index, list(ranked.chosen), dict(ranked.reasons), dict(ranked.decided))
            _adopt(made, adopted)
            truth = {e: sum(1 << k for k, b in enumerate(index.bits) if b is not None and (held >> b) & 1)
                     for e, held in satisfied.items()}
            outcome = Outcome(["a demonstrated call"] * len(index.bits), truth, (1 << len(index.bits)) - 1, 0, [])
            out[action] = made.separation(outcome, [], set(), False)
    return out


def _adopt(made: Made, adopted: Mapping[str, str]) -> None:
    satisfied = {r.expression: r.satisfied for r in made.results}
    for e, other in adopted.items():
        made.adopt(e, satisfied[e], f"kept: the labelled calls of {other} chose it (it refuses calls labelled "
                                    f"'refuse' there); it holds at every call to allow here")
