"""Where a string argument of a tool call came from, at every demonstrated call: conditions on its provenance.

Policies of tool-calling agents say it in many words ("only the verified customer's cards", "only a slot the
search offered", "the patient found by their email"); the logs show it as an argument that, at every demonstrated
call, equals something an earlier read returned. Three sources, each written as plain Python the embedded guard
runs (`self.seen[tool]`: the records of a read's results, a scalar result being its own record):

- `owned`: listed in a list field of a record an earlier read returned
  (`any(card_id in y['card_ids'] for y in self.seen['get_customer_profile'])`: the caller's own records);
- `offered`: one field of a record an earlier read listed
  (`slot_id in [y['slot_id'] for y in self.seen['search_available_slots']]`: only what was offered);
- `found`: the scalar result of an earlier look-up (`patient_id in self.seen['find_patient_by_email']`: the id the
  caller was identified by), or an id field of an object an earlier read returned that is not the argument's own
  record (`customer_id in [y['customer_id'] for y in self.seen['verify_identity']]`: the verified customer).

Only the demonstrated calls count (`ToolFacts.demonstrated_calls`): a labelled call to refuse is exactly where the
argument came from elsewhere, and must not erase the condition that refuses it. At most MAX_SOURCES atoms an
argument and kind.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence

from precond.engine.candidates.tool_facts import Seen, ToolFacts

SEEN = "self.seen"
MAX_SOURCES = 3


def provenance(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """The provenance atoms of one action's arguments: owned, offered, found."""
    return [*owned(facts, action, params), *offered(facts, action, params), *found(facts, action, params)]


def offered(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """A field every listed record of that tool holds, so that the condition reads the same on every record,
    whatever the argument is named (`new_slot_id`)."""
    def origin(call: Seen, param: str) -> set[tuple[str, str]]:
        value = call.args.get(param)
        return {(tool, name) for tool, rows in call.listed.items() if tool != action
                for row in rows for name, item in row.items() if isinstance(value, str) and item == value
                and facts.records.get(tool, Counter())[name] == facts.records.get(tool, Counter())[""]}

    return _at_every_call(facts.demonstrated_calls(action), params, origin,
                          lambda param, tool, name: f"{param} in [y[{name!r}] for y in {SEEN}[{tool!r}]]")


def owned(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """A record (a dict) an earlier read returned, not the read the argument itself keys: its result is the record,
    not its owner."""
    def origin(call: Seen, param: str) -> set[tuple[str, str]]:
        value = call.args.get(param)
        return {(tool, name) for (tool, _), result in call.results.items() if isinstance(result, dict)
                for name, item in result.items() if isinstance(item, list) and isinstance(value, str)
                and value in item and facts.key_param.get(tool) != param and tool not in facts.records}

    return _at_every_call(facts.demonstrated_calls(action), params, origin,
                          lambda param, tool, name: f"any({param} in y[{name!r}] for y in {SEEN}[{tool!r}])")


def found(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """A read whose successful result is a plain string (an id a look-up by email or name returned), other than
    the action itself."""
    def origin(call: Seen, param: str) -> set[tuple[str, str]]:
        value = call.args.get(param)
        if not isinstance(value, str):
            return set()
        scalars = {(tool, "") for (tool, _), result in call.results.items() if tool != action and result == value}
        fields = {(tool, name) for (tool, _), result in call.results.items() if isinstance(result, dict)
                  and tool != action and facts.key_param.get(tool) != param for name, item in result.items()
                  if item == value and _identifier(name) and _in_every_object(facts, tool, name)}
        return scalars | fields

    def atom(param: str, tool: str, name: str) -> str:
        return f"{param} in {SEEN}[{tool!r}]" if not name else f"{param} in [y[{name!r}] for y in {SEEN}[{tool!r}]]"

    return _at_every_call(facts.demonstrated_calls(action), params, origin, atom)


def _identifier(name: str) -> bool:
    """A field that names a record (`customer_id`, `id`): a cabin or a date equal to one read is what the logs
    happened to keep, not where the argument must come from."""
    return name == "id" or name.endswith("_id")


def _in_every_object(facts: ToolFacts, tool: str, name: str) -> bool:
    """Every object the read returned held the field with a plain value: `y[name]` never fails on `self.seen`."""
    return isinstance(name, str) and sum(facts.values.get(tool, {}).get(name, Counter()).values()) \
        == facts.dict_results[tool] > 0


def _at_every_call(calls: Sequence[Seen], params: Sequence[str],
                   origin: Callable[[Seen, str], set[tuple[str, str]]],
                   atom: Callable[[str, str, str], str]) -> list[str]:
    """For each argument, the (tool, field) sources `origin` finds at every one of `calls` (none when there is no
    call), written as atoms, at most MAX_SOURCES an argument."""
    atoms: list[str] = []
    for param in params:
        common: set[tuple[str, str]] | None = None
        for call in calls:
            here = origin(call, param)
            common = here if common is None else common & here
        atoms += [atom(param, tool, name) for tool, name in sorted(common or ())][:MAX_SOURCES]
    return atoms
