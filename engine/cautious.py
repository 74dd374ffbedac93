"""The cautious criterion (the default): rules that hold up in the states a guard exists for.

The paper's criteria are judged on test dialogs from the same generator as the demonstrations, where a rule
merely correlated with the true requirement scores perfectly. A guard is consulted where that correlation
breaks: the user confirms before their identity was checked, the search is asked for before the intent was
stated. The demonstrations cannot tell a requirement from a correlate there, so this criterion does not pick
the permissive side silently. For each action it keeps:

1. *Established* rules: the conditions the observations since the agent's previous turn made true or renewed
   (`ranking.enabling_rate` with `engine/freshness.py`), among themselves subsumption-minimal (a trigger that
   a phase subsumes on the demonstrated points is still the trigger: a success notice follows the success,
   not the confirmation before it). Conditions on the action's own arguments count as established.
2. When no single condition is such a trigger at the calls: a *disjunction* of triggers, found by a greedy
   cover of the calls with the conditions made true before them ("anything else?" after a "no, thanks" or
   after "that's all"); for a tool call each term is a conjunction (two alternative credential sets).
3. *Assumed* rules, for tool calls only (an action whose calls a service answers, like a search or a card
   block): every positive fact (a slot informed, an identity verified, an intent stated: `polarity`) that held
   at every demonstrated call, though it was true long before (a phase), true almost everywhere (not separated
   from chance) or implied by another rule *on the demonstrated points* (which is not implication). Nothing
   shows the call can happen without it, so the guard keeps it and says so; a reviewer can drop it.
   Dialog acts do not get them: acting on a phase there costs a re-ask, not a blocked card, and they are
   what an assistant says most (docs/results.md measures both sides).

Actions demonstrated too thinly to learn from get every positive fact their few calls share, assumed
(`thin_rules`); never-demonstrated actions are `options.unseen`'s business (engine.engine).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from engine.evidence import CHANCE_ALPHA, Evidence
from engine.ranking import (
    ActionEvidence,
    Candidate,
    Cluster,
    cluster,
    enabled_at,
    enabling_rate,
    informative,
    subsumption,
)
from sandbox.types import Point
from schemas.api import Decided

MAX_TERMS = 3
MAX_DISJUNCTION_ATOMS = 400  # conditions the cover looks at; more are left out and the report says so


@dataclass(frozen=True)
class Choice:
    """What an action keeps and how each kept rule was decided (keyed by its expression)."""

    chosen: list[Cluster]
    decided: dict[str, Decided] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)  # expression -> why it was kept, in words
    search: str = ""  # the disjunction search stopped at its bound: what it looked at, in words


def polarity(expression: str) -> str:
    """'positive': asserts that something was established (a flag set, a slot informed, a result present, an
    argument among what was offered); 'negative': that something has not happened (yet), or is absent."""
    try:
        node = ast.parse(expression, mode="eval").body
    except (SyntaxError, RecursionError, ValueError):
        return "negative"
    return "negative" if _negated(node) else "positive"


def _negated(node: ast.expr) -> bool:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        return True
    if isinstance(node, ast.BoolOp):
        return any(_negated(v) for v in node.values)
    if isinstance(node, ast.Compare):
        return any(isinstance(op, ast.NotEq | ast.NotIn) for op in node.ops) or any(
            isinstance(op, ast.Is) and isinstance(c, ast.Constant) and c.value is None
            for op, c in zip(node.ops, node.comparators, strict=True))
    return False


def triggers(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    index = {point: bit for bit, point in enumerate(evidence.points)}
    enabled = [c for c in clusters if enabling_rate(c, evidence, index) > 0]
    return subsumption(enabled, evidence.occurrence_mask)


def choose(clusters: Sequence[Cluster], common: Sequence[Cluster], atoms: Sequence[Cluster],
           evidence: ActionEvidence, tool_call: bool) -> Choice:
    """`clusters`: the candidates that passed validation (triggers come from these); `common`: those plus the
    ones true almost everywhere (not separated from chance), which a tool call may still require; `atoms`:
    every judged candidate, for the disjunction's terms (each alone is refuted by the calls the others cover)."""
    chosen = triggers(clusters, evidence)
    decided: dict[str, Decided] = {c.representative.expression: "established" for c in chosen}
    notes: dict[str, str] = {}
    search = ""
    if not chosen:
        found, note, cut = disjunction(atoms, evidence, tool_call)
        if found is not None:
            chosen = [found]
            decided[found.representative.expression] = "established"
            notes[found.representative.expression] = note
        if cut:
            search = f"disjunction search bounded: {note}"
    if tool_call:
        for c in assumed(common, evidence, {c.satisfied for c in chosen}):
            chosen.append(c)
            decided[c.representative.expression] = "assumed"
    return Choice(chosen, decided, notes, search)


def assumed(clusters: Sequence[Cluster], evidence: ActionEvidence, kept: set[int]) -> list[Cluster]:
    """Positive facts that held at every call and are not already kept."""
    mask = evidence.occurrence_mask
    return [c for c in clusters if c.satisfied not in kept and not mask & ~c.satisfied
            and polarity(c.representative.expression) == "positive"]


def thin_rules(candidates: Sequence[Candidate], evidence: ActionEvidence, n_points: int, tool_call: bool
               ) -> list[Cluster]:
    """An action seen once or twice: the positive facts its calls share that enabled them (for a tool call,
    every positive fact they share): the rule the same criterion would keep, on evidence too thin to call it
    established."""
    mask = evidence.occurrence_mask
    every = [c for c in candidates if mask and not mask & ~c.satisfied]
    shared = [c for c in informative(cluster(every), n_points) if polarity(c.representative.expression) == "positive"]
    if tool_call:
        return shared
    index = {point: bit for bit, point in enumerate(evidence.points)}
    return [c for c in shared if enabling_rate(c, evidence, index) > 0]


def disjunction(atoms: Sequence[Cluster], evidence: ActionEvidence, tool_call: bool
                ) -> tuple[Cluster | None, str, bool]:
    """A greedy cover of the calls by the positive conditions made true just before them, at most MAX_TERMS
    terms, each covering calls no earlier term covers; None unless two or more terms cover every call. Also
    what happened, in words, and whether the search stopped at MAX_DISJUNCTION_ATOMS."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    positive = [c for c in atoms if polarity(c.representative.expression) == "positive"]
    cut = len(positive) > MAX_DISJUNCTION_ATOMS
    positive = positive[:MAX_DISJUNCTION_ATOMS]
    made = {c.satisfied: {k for k, fate in enumerate(enabled_at(c, evidence, index)) if fate} for c in positive}
    bits = [index.get(occ) for occ in evidence.occurrences]
    uncovered = {k for k, bit in enumerate(bits) if bit is not None}
    terms: list[Cluster] = []
    while uncovered and len(terms) < MAX_TERMS:
        best = max(positive, key=lambda c: (len(made[c.satisfied] & uncovered),
                                            -len(c.representative.expression)), default=None)
        if best is None or not made[best.satisfied] & uncovered:
            break
        terms.append(best)
        uncovered -= {k for k in uncovered if (best.satisfied >> (bits[k] or 0)) & 1}
    budget = f" (the search looked at the first {MAX_DISJUNCTION_ATOMS} of {len(atoms)} conditions)" if cut else ""
    if uncovered or len(terms) < 2:
        return None, f"no disjunction of at most {MAX_TERMS} triggers covers every call{budget}", cut
    conjuncts = [_term(t, positive, evidence, index, bits) if tool_call else [t] for t in terms]
    expression = " or ".join(_parenthesised(term) for term in conjuncts)
    satisfied = 0
    for term in conjuncts:
        both = (1 << len(evidence.points)) - 1
        for c in term:
            both &= c.satisfied
        satisfied |= both
    mask = evidence.occurrence_mask
    counts = Evidence(mask.bit_count(), (satisfied & mask).bit_count(), len(evidence.points) - mask.bit_count(),
                      (satisfied & ~mask).bit_count())
    if counts.chance() >= CHANCE_ALPHA:
        return None, (f"the disjunction {expression!r} holds about as often where the action was not taken "
                      f"(p = {counts.chance():.2f}): not separated from chance{budget}"), cut
    note = f"a disjunction: each term was made true before the calls it covers{budget}"
    return Cluster((Candidate(expression, terms[0].representative.source, satisfied),)), note, cut


def _term(trigger: Cluster, positive: Sequence[Cluster], evidence: ActionEvidence, index: Mapping[Point, int],
          bits: Sequence[int | None]) -> list[Cluster]:
    """A tool call's term: the trigger and every positive fact true at every call the trigger enabled."""
    covered = [bits[k] for k, fate in enumerate(enabled_at(trigger, evidence, index)) if fate and bits[k] is not None]
    mask = 0
    for bit in covered:
        mask |= 1 << (bit or 0)
    everything = (1 << len(evidence.points)) - 1
    shared = [c for c in positive if c is not trigger and not mask & ~c.satisfied and c.satisfied != everything]
    return [trigger, *shared]


def _parenthesised(term: Sequence[Cluster]) -> str:
    text = " and ".join(c.representative.expression if len(term) == 1 else f"({c.representative.expression})"
                        for c in term)
    return f"({text})" if len(term) > 1 else text
