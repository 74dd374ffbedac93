"""Allowances by category (precond/engine/candidates/tool_conditions.py `keys`,
precond/engine/judging/allowance_tables.py `table`):
free items per item looked up by a field of a read the call names or an argument of the call, learned from
labelled calls only where one allowance for every call cannot separate them; a value no call shows falls back."""

from __future__ import annotations

import ast
import json
from collections.abc import Iterator
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.candidates import tool_conditions, tool_facts
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.guard import Guard
from precond_client.schemas import CheckRequest, InferRequest

TYPES = {"guests": "array", "passes": "integer", "paid": "integer"}
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": TYPES.get(p, "string")} for p in params}, "required": list(params)}}}
    for name, params in [("get_member", ("member_id",)),
                         ("book_session", ("member_id", "session", "guests", "passes", "paid"))]]
BOOK = "AGENT.book_session"
TABLE = ("member_id in self.results['get_member'] and (self.results['get_member'][member_id]['tier'] == 'gold' "
         "and paid == max(0, passes - 2 * len(guests)) or self.results['get_member'][member_id]['tier'] not in "
         "('gold',) and paid == max(0, passes - 0 * len(guests)))")
FLAT = "paid == max(0, passes - 1 * len(guests))"


def call(name: str, arguments: dict[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": name, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def booking(tier: str, guests: int, passes: int, paid: int, session: str = "yoga", read: bool = True
            ) -> list[dict[str, object]]:
    """A member of `tier` books a session for `guests` guests using `passes` guest passes, `paid` of them paid."""
    member = call("get_member", {"member_id": "m1"}, {"member_id": "m1", "tier": tier}) if read else []
    arguments = {"member_id": "m1", "session": session, "guests": [{"name": f"g{k}"} for k in range(guests)],
                 "passes": passes, "paid": paid}
    return [{"role": "user", "content": "book me in"}, *member, *call("book_session", arguments, {})]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def line_of(program: str) -> int:
    return next(n for n, text in enumerate(program.splitlines(), 1) if "book_session(" in text)


def infer(engine: Engine, demos: list[list[dict[str, object]]], runs: list[tuple[list[dict[str, object]], str]]
          ) -> tuple[str, list[str], Any]:
    converted, labelled = convert(demos, TOOLS), convert([r for r, _ in runs], TOOLS)
    counterexamples = [{"program": t.program, "calls": [{"line": line_of(t.program), "verdict": v, "name": t.name}]}
                       for t, (_, v) in zip(labelled.trajectories, runs, strict=True)]
    return converted.spec, [t.name for t in labelled.trajectories], engine.infer(InferRequest.model_validate({
        "spec": converted.spec, "demonstrations": [t.program for t in converted.trajectories], "actions": [BOOK],
        "options": {"generators": ["enumerate"]}, "counterexamples": counterexamples}))


def judged(engine: Engine, spec: str, preconditions: dict[str, list[str]], calls: list[list[dict[str, object]]]
           ) -> list[bool]:
    """Each booking judged by the service and by the embedded guard's restricted interpreter, which agree."""
    guard, verdicts = Guard(spec, preconditions), []
    for run in calls:
        lines = convert([run], TOOLS).trajectories[0].program.splitlines()
        at = line_of("\n".join(lines)) - 1
        allowed = engine.check(CheckRequest(spec=spec, preconditions=preconditions,
                                            history="\n".join(lines[:at]) + "\n", calls=[lines[at]])).results[0].allowed
        booked = run[-2]["tool_calls"][0]["function"]  # type: ignore[index]
        assert guard.check(run[:-2], booked["name"], booked["arguments"]).allowed == allowed
        verdicts.append(allowed)
    return verdicts


def test_free_passes_by_tier_are_learned_where_one_allowance_cannot_separate(engine: Engine) -> None:
    """Gold members get 2 free passes a guest, basic members none: no one allowance holds at every call to allow,
    so the table by the member's tier is learned. A basic member's 2 free passes for one guest is refused although
    a gold member's is allowed; a tier no call shows ('platinum') gets the fallback, and the evidence says so."""
    demos = [booking("gold", 1, 1, 0), booking("basic", 1, 0, 0), booking("gold", 2, 4, 0)]
    spec, names, inferred = infer(engine, demos, [
        (booking("gold", 1, 2, 0), "allow"), (booking("gold", 2, 5, 1), "allow"),
        (booking("basic", 1, 1, 1), "allow"), (booking("basic", 2, 3, 3, "spin"), "allow"),
        (booking("basic", 1, 2, 0), "refuse"), (booking("gold", 1, 3, 0), "refuse"),
        (booking("gold", 1, 1, 0, read=False), "refuse")])
    rules = inferred.preconditions[BOOK]
    assert TABLE in rules
    assert not any(rule.startswith("paid == max(0, ") for rule in rules)
    evidence = inferred.evidence[BOOK][TABLE]
    assert sorted(evidence.refuses) == sorted(names[4:])  # the one without a read too: the tier is read
    [report] = [c for c in inferred.candidates[BOOK] if c.assertion == TABLE]
    assert "a tier no labelled or demonstrated call shows gets 0" in (report.reason or "")
    assert judged(engine, spec, inferred.preconditions, [
        booking("basic", 1, 2, 0), booking("gold", 1, 2, 0), booking("basic", 1, 2, 2), booking("gold", 3, 7, 1),
        booking("platinum", 1, 1, 1), booking("platinum", 1, 1, 0)]) == [False, True, True, True, True, False]


def test_free_passes_by_session_are_read_off_the_call(engine: Engine) -> None:
    """Every tier gets 1 free pass a guest for yoga and none for spin: the table is keyed by the call's own
    argument, never by the tier, which does not tell the labelled calls apart."""
    demos = [booking("gold", 1, 1, 0), booking("basic", 1, 0, 0, "spin")]
    spec, names, inferred = infer(engine, demos, [
        (booking("gold", 2, 3, 1), "allow"), (booking("basic", 1, 2, 2, "spin"), "allow"),
        (booking("basic", 2, 2, 0), "allow"), (booking("gold", 1, 1, 0, "spin"), "refuse"),
        (booking("basic", 1, 2, 2), "refuse"), (booking("gold", 1, 1, 0, read=False), "refuse")])
    table = [rule for rule in inferred.preconditions[BOOK] if "* len(guests)" in rule]
    assert table == ["session == 'yoga' and paid == max(0, passes - 1 * len(guests)) or session not in ('yoga',) "
                     "and paid == max(0, passes - 0 * len(guests))"]
    assert sorted(inferred.evidence[BOOK][table[0]].refuses) == sorted(names[3:5])
    assert judged(engine, spec, inferred.preconditions, [booking("gold", 1, 1, 0, "spin"), booking(
        "basic", 1, 1, 0), booking("gold", 1, 1, 0, "boxing"), booking("gold", 1, 1, 1, "boxing")]) == [
        False, True, False, True]


def test_one_allowance_for_every_tier_is_kept_flat(engine: Engine) -> None:
    """Every tier gets 1 free pass a guest: the flat allowance separates the labelled calls, and no table is
    learned (fewer conditions)."""
    demos = [booking("gold", 1, 1, 0), booking("basic", 1, 0, 0), booking("gold", 2, 2, 0)]
    _, _, inferred = infer(engine, demos, [
        (booking("gold", 2, 3, 1), "allow"), (booking("basic", 1, 2, 1), "allow"),
        (booking("basic", 1, 2, 0), "refuse"), (booking("gold", 1, 3, 0), "refuse"),
        (booking("gold", 1, 1, 0, read=False), "refuse")])
    rules = inferred.preconditions[BOOK]
    assert FLAT in rules
    assert not any(" in ('" in rule or "not in (" in rule for rule in rules)


def test_free_passes_by_tier_and_session_need_both_categories(engine: Engine) -> None:
    """Gold members get 2 free passes a guest for yoga and 1 for spin, basic members 1 and none: neither the tier
    nor the session alone gives one k to the calls to allow of each value, and a call of every cell is refused
    (no category alone separates), so the table is keyed by both."""
    demos = [booking("gold", 1, 2, 0), booking("basic", 1, 0, 0, "spin")]
    spec, names, inferred = infer(engine, demos, [
        (booking("gold", 1, 3, 1), "allow"), (booking("gold", 1, 2, 1, "spin"), "allow"),
        (booking("basic", 1, 2, 1), "allow"), (booking("basic", 1, 1, 1, "spin"), "allow"),
        (booking("basic", 1, 1, 0, "spin"), "refuse"), (booking("gold", 1, 3, 0), "refuse"),
        (booking("gold", 1, 2, 0, "spin"), "refuse"), (booking("basic", 1, 2, 0), "refuse"),
        (booking("gold", 1, 1, 0, read=False), "refuse")])
    [table] = [rule for rule in inferred.preconditions[BOOK] if "* len(guests)" in rule]
    both = "(self.results['get_member'][member_id]['tier'], session)"
    assert f"{both} == ('gold', 'yoga') and paid == max(0, passes - 2 * len(guests))" in table
    assert f"{both} in (('basic', 'yoga'), ('gold', 'spin')) and paid == max(0, passes - 1 * len(guests))" in table
    assert sorted(inferred.evidence[BOOK][table].refuses) == sorted(names[4:])
    assert table.endswith(f"{both} not in (('gold', 'yoga'), ('basic', 'yoga'), ('gold', 'spin')) and "
                          "paid == max(0, passes - 0 * len(guests)))")
    assert judged(engine, spec, inferred.preconditions, [
        booking("gold", 1, 2, 1, "spin"), booking("basic", 1, 1, 0, "spin"), booking("gold", 1, 3, 1),
        booking("basic", 1, 3, 1)]) == [True, False, True, False]


def test_the_categories_are_arguments_of_a_few_strings_never_an_id_and_never_ranked() -> None:
    """The session (two values) is a category; the member's id names a read (an identity, not a category), and
    the tier is the read's field, proposed with the read's other fields. The argument's categories are left out
    of the ranking like the allowance they key (`arithmetic`)."""
    converted = convert([booking("gold", 1, 1, 0), booking("basic", 1, 0, 0, "spin"),
                         booking("basic", 2, 2, 2, "spin")], TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    found = tool_conditions.keys(facts, "book_session", spec.methods[BOOK].positional)
    assert found == ["session in ('spin',)", "session in ('yoga',)"]
    assert all(tool_conditions.arithmetic(atom) for atom in found)
    assert tool_conditions.key(found[0]) == (None, "session", "spin")
    assert not tool_conditions.arithmetic("session == 'spin'")
