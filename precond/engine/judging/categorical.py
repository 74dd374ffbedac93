"""The state a tool call moves its record out of, or a capacity it stays within, kept where the demonstrations
cannot tell it from the read.

A policy says "freeze only an active card", "cancel only a booked appointment"; the logs show every freeze after a
read of a card whose status was `active`, and a result that shows it `frozen`. At every point the sandbox judged,
`card_id in self.results['get_card_details']` and `... and self.results['get_card_details'][card_id]['status']
in ('active',)` (`candidates.tool_transitions`) hold alike (no demonstration read a frozen card and then stood
before a freeze of it), so both fall in one cluster, and its representative, the shorter text, is the bare read:
a guard that freezes frozen cards. The cautious criterion keeps what held at every call and nothing shows the call
can do without (`cautious` module docstring, 3.); here that is the state the call moves out of.

So, for a tool call, each chosen cluster also keeps its members that are its representative and such a transition
(the one-value tuple form only the transition generator writes): assumed, with a note. The same holds for an
argument bounded by a capacity of the record it names (`new_limit <= ...[card_id]['max_limit']`, `extra_days <=
...['extension_days_left']`: a field named max, left, remaining, balance, available or capacity): every
demonstrated call stayed within it, and the policies that keep such a field say what it caps. Such a rule is a
reading of the logs: a labelled call it refuses is still searched for a condition of its own
(`counterexamples.separate`), so that labels teach what they show whatever the refinement refuses besides.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Mapping
from dataclasses import replace

from precond.engine.judging.cautious import Choice
from precond.engine.judging.ranking import Cluster

CAPACITY = re.compile(r"(?:^|_)(?:max|maximum|left|remaining|balance|available|cap|capacity)(?:$|_)")
MARK = "every demonstrated call found the record so"
NOTE = f"assumed: {MARK}; the demonstrations cannot tell it from the read it refines ({{rep}})"


def refined(choice: Choice) -> Choice:
    """`choice` with, beside each chosen cluster, its transition members (module docstring), decided assumed."""
    kept = {c.representative.expression for c in choice.chosen}
    extra: list[Cluster] = []
    notes = dict(choice.notes)
    decided = dict(choice.decided)
    for group in choice.chosen:
        rep = group.representative.expression
        for member in group.members:
            if member.expression not in kept and _transition_of(member.expression, rep):
                extra.append(Cluster((member,)))
                kept.add(member.expression)
                decided[member.expression] = "assumed"
                notes[member.expression] = NOTE.format(rep=rep)
    if not extra:
        return choice
    return replace(choice, chosen=[*choice.chosen, *extra], decided=decided, notes=notes)


def refinements(reasons: Mapping[str, str]) -> set[str]:
    """The kept rules that are transitions kept beside their read, by the reason they were kept for."""
    return {e for e, why in reasons.items() if MARK in why}


def _transition_of(expression: str, representative: str) -> bool:
    """`expression` is `representative and <field> in (<one string>,)`, or `representative and <argument> <=
    <field>` where the field names a capacity (`max_limit`, `extension_days_left`, `balance`)."""
    prefix = f"{representative} and "
    if not expression.startswith(prefix):
        return False
    try:
        node = ast.parse(expression[len(prefix):], mode="eval").body
    except (SyntaxError, RecursionError, ValueError):
        return False
    if not (isinstance(node, ast.Compare) and len(node.ops) == 1):
        return False
    right = node.comparators[0]
    if isinstance(node.ops[0], ast.LtE):
        return (isinstance(node.left, ast.Name) and isinstance(right, ast.Subscript)
                and isinstance(right.slice, ast.Constant) and isinstance(right.slice.value, str)
                and bool(CAPACITY.search(right.slice.value)))
    return (isinstance(node.ops[0], ast.In) and isinstance(node.left, ast.Subscript) and isinstance(right, ast.Tuple)
            and len(right.elts) == 1 and isinstance(right.elts[0], ast.Constant)
            and isinstance(right.elts[0].value, str))
