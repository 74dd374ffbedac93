"""The states writes move their records out of: `... and self.results['get_card_details'][card_id]['status'] in
('active',)` for a freeze whose every demonstrated result shows the card `frozen`.

A write that changes a record's state field (a card's status, an order's, an appointment's) has the state it
moves out of as a precondition: freeze an active card, cancel a pending order or a booked appointment. The logs
show it as a field that, at every demonstrated call of a write, the read of the record held at one value and the
write's own result showed at another. Such a field is a lifecycle state, not an attribute that happened to be alike
in the logs (a cabin, a card type): no demonstrated call of that write left it where it was. Every write on such a
record whose demonstrated calls all found it in that state gets the condition too (an order's address is changed
while it is pending, an appointment moved while it is booked): the logs show writes in that state only, and the
state machine's other writes leave it. A write the policy allows in another state too (a frozen card's limit) is
refused there until a label or a demonstration shows it: the rule is kept as assumed, and says so.

The condition is written with a one-value tuple (`in ('active',)`), unlike the field equalities the enumerator
proposes beside it (`== 'active'`), because the demonstrations cannot tell it from the bare read (no demonstration
reads a frozen card and then stands before a freeze of it): both fall in one cluster, whose representative is the
shorter, and the ranking keeps the transition beside it by its form (`judging.categorical`). At least MIN_CALLS
demonstrated calls of the write that moves the state and of the write that gets the condition: one call cannot
tell a state from a coincidence.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from precond.engine.candidates.tool_facts import ToolFacts

RESULTS = "self.results"
MIN_CALLS = 2


def transitions(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """One condition per (read, field, state): the states writes move their records out of (`moved_out_of`)
    that every demonstrated call of this write found its record in (the action's own transition, or a write that
    changes the record while it stays in that state: an address changed while the order is pending)."""
    calls = facts.demonstrated_calls(action)
    if action not in facts.writes or len(calls) < MIN_CALLS:
        return []
    atoms = []
    for read, name, value in sorted(moved_out_of(facts)):
        key = facts.key_param.get(read)
        if key is not None and key in params and all(
                _field(c.results.get((read, c.args.get(key))), name) == value for c in calls):
            table = f"{RESULTS}[{read!r}]"
            atoms.append(f"{key} in {table} and {table}[{key}][{name!r}] in ({value!r},)")
    return atoms


def moved_out_of(facts: ToolFacts) -> set[tuple[str, str, str]]:
    """(read, field, value): a write that, at each of its (at least MIN_CALLS) demonstrated calls, found the field
    of the record it names at that one value and left it at another."""
    found = set()
    for write in facts.writes:
        calls = facts.demonstrated_calls(write)
        moved = [m for m in facts.moves.get(write, []) if facts.demonstrated is None or m.run < facts.demonstrated]
        by_field: dict[tuple[str, str], list[tuple[str, object]]] = defaultdict(list)
        for move in moved:
            by_field[(move.read, move.name)].append((move.before, move.after))
        for (read, name), pairs in by_field.items():
            before = {b for b, _ in pairs}
            if len(calls) >= MIN_CALLS and len(pairs) == len(calls) and len(before) == 1 \
                    and all(b != a for b, a in pairs):
                found.add((read, name, next(iter(before))))
    return found


def _field(record: object, name: str) -> object:
    return record.get(name) if isinstance(record, dict) else None
