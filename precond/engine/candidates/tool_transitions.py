"""The state an action moves a record out of: `... and self.results['get_card_details'][card_id]['status'] in
('active',)` for a freeze whose every demonstrated result shows the card `frozen`.

A write that changes a record's state field (a card's status, an order's, an appointment's) has the state it
moves out of as a precondition: freeze an active card, cancel a pending order or a booked appointment. The logs
show it as a field that, at every demonstrated call of the action, the read of the record held at one value and
the action's own result showed at another. Such a field is a lifecycle state, not an attribute that happened to be
alike in the logs (a cabin, a card type): no demonstrated call of the action left it where it was.

The condition is written with a one-value tuple (`in ('active',)`), unlike the field equalities the enumerator
proposes beside it (`== 'active'`), because the demonstrations cannot tell it from the bare read (no demonstration
reads a frozen card and then stands before a freeze of it): both fall in one cluster, whose representative is the
shorter, and the ranking keeps the transition beside it by its form (`judging.categorical`). At least MIN_CALLS
demonstrated calls: one call cannot tell a transition from a coincidence.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from precond.engine.candidates.tool_facts import ToolFacts

RESULTS = "self.results"
MIN_CALLS = 2


def transitions(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """One condition per (read, field) the action moved out of one value at every demonstrated call."""
    calls = facts.demonstrated_calls(action)
    moved = [m for m in facts.moves.get(action, []) if facts.demonstrated is None or m.run < facts.demonstrated]
    if len(calls) < MIN_CALLS:
        return []
    by_field: dict[tuple[str, str], list[tuple[str, object]]] = defaultdict(list)
    for move in moved:
        by_field[(move.read, move.name)].append((move.before, move.after))
    atoms = []
    for (read, name), pairs in sorted(by_field.items()):
        key = facts.key_param.get(read)
        before = {b for b, _ in pairs}
        if key in params and len(pairs) == len(calls) and len(before) == 1 and all(b != a for b, a in pairs):
            value = next(iter(before))
            table = f"{RESULTS}[{read!r}]"
            atoms.append(f"{key} in {table} and {table}[{key}][{name!r}] in ({value!r},)")
    return atoms
