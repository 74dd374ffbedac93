"""Joins of a call's arguments with what earlier reads returned (precond/engine/candidates/tool_relations.py `variants`,
`_recorded`, `scalar_kinds`) and conditions one action's labels chose, adopted by another action
(precond/engine/judging/shared_rules.py), on a library desk agent written from scratch: a member swaps copies of a loan
for
other copies of the same title, paying the fee with a card; a loan can be swapped or extended only while open."""

from __future__ import annotations

import ast
import json
from collections.abc import Iterator, Mapping
from types import SimpleNamespace

import pytest

from precond.convert.openai import convert
from precond.engine.candidates import tool_facts
from precond.engine.candidates.tool_relations import labels_only, relations
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import Frame, Scope, compile_rule
from precond_client.schemas import CheckRequest, InferRequest

PARAMS = {"get_loan": ("loan_id",), "get_title": ("title_id",), "extend_loan": ("loan_id",),
          "swap_copies": ("loan_id", "copy_ids", "new_copy_ids", "card_id")}
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "array" if p.endswith("ids") else "string"} for p in params},
    "required": list(params)}}} for name, params in PARAMS.items()]
WRITES = {"swap_copies", "extend_loan"}
SWAP, EXTEND = "AGENT.swap_copies", "AGENT.extend_loan"


def call(tool: str, arguments: Mapping[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": tool, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def desk_run(n: int, new: str | None = None, card: str | None = None, state: str = "open",
             act: bool = True) -> list[dict[str, object]]:
    """Loan L{n} holds copy c{n}a of title t{n} (copies c{n}a..c{n}c); title u{n} (copies d{n}a, d{n}b) is read
    too. Where `act`, the member swaps c{n}a for `new` (c{n}c), paying with `card` (the loan's own card_{n}, or
    gift_{n}), and extends the loan."""
    loan = {"loan_id": f"L{n}", "state": state, "copies": [{"copy_id": f"c{n}a", "title_id": f"t{n}"}],
            "payments": [{"card_id": f"card_{n}", "amount": 5}]}
    titles: dict[str, dict[str, object]] = {"copies": {f"c{n}{c}": {"shelf": c} for c in "abc"}}
    steps: list[dict[str, object]] = [
        {"role": "user", "content": f"swap my loan L{n}"}, *call("get_loan", {"loan_id": f"L{n}"}, loan),
        *call("get_title", {"title_id": f"t{n}"}, titles),
        *call("get_title", {"title_id": f"u{n}"}, {"copies": {f"d{n}{c}": {"shelf": c} for c in "ab"}})]
    if act:
        swap = {"loan_id": f"L{n}", "copy_ids": [f"c{n}a"], "new_copy_ids": [new or f"c{n}c"],
                "card_id": card or (f"card_{n}" if n % 2 else f"gift_{n}")}
        steps += [{"role": "user", "content": "yes"}, *call("swap_copies", swap, {"ok": True}),
                  {"role": "user", "content": "yes"}, *call("extend_loan", {"loan_id": f"L{n}"}, {"ok": True})]
    return steps


def swap_relations(runs: list[list[dict[str, object]]]) -> list[str]:
    converted = convert(runs, TOOLS, writes=WRITES)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    return relations(facts, "swap_copies", spec.methods[SWAP].positional)


def same_title(found: list[str]) -> list[str]:
    return [a for a in found if "new_copy_ids if x in" in a]


def test_new_items_of_the_same_entry_as_the_old_ones_are_proposed_and_judged() -> None:
    [atom] = same_title(swap_relations([desk_run(n) for n in range(6)]))
    titles: dict[str, object] = {"t1": {"copies": {"c1a": {}, "c1c": {}}}, "u1": {"copies": {"d1a": {}}}}
    rule = compile_rule(atom, Scope(AGENT_SHAPE, PARAMS["swap_copies"]))
    state = SimpleNamespace(results={"get_title": titles}, changes={}, errors={}, seen={}, last_ok=True,
                            user=SimpleNamespace(messages=1, last_said="yes"))
    judged = {new: rule(Frame(state, ("L1", ["c1a"], [new], "card_1"))) for new in ("c1c", "d1a", "zz")}
    assert judged == {"c1c": True, "d1a": False, "zz": False}  # a copy of the other title; one never read


def test_a_join_a_demonstrated_call_breaks_is_not_proposed() -> None:
    assert not same_title(swap_relations([desk_run(n) for n in range(5)] + [desk_run(7, new="d7a")]))


def test_an_argument_among_a_listed_field_and_its_kinds() -> None:
    found = swap_relations([desk_run(n) for n in range(6)])
    listed = "[y['card_id'] for y in self.results['get_loan'][loan_id]['payments']]"
    assert f"loan_id in self.results['get_loan'] and card_id in {listed}" in found  # the card the loan was paid by
    assert {"'card_' in card_id", "'gift_' in card_id"} <= set(found)  # two kinds of card the calls show
    assert not any(" in card_id" in a for a in swap_relations([desk_run(n, card=f"card_{n}") for n in range(6)]))


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, None)


def test_a_condition_one_actions_labels_chose_is_adopted_where_every_call_to_allow_meets_it(engine: Engine) -> None:
    demos = convert([desk_run(n) for n in range(6)] + [desk_run(n, state="closed", act=False)
                                                       for n in (6, 7)], TOOLS, writes=WRITES)
    closed = convert([desk_run(n, state="closed") for n in (8, 9)], TOOLS, writes=WRITES).trajectories
    swaps = [k for k, line in enumerate(closed[0].program.splitlines(), 1) if ".swap_copies(" in line]
    labels = [{"program": t.program, "calls": [{"line": swaps[0], "verdict": "refuse", "name": f"closed {t.name}"}]}
              for t in closed]
    response = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [SWAP, EXTEND],
        "options": {"generators": ["enumerate"]}, "counterexamples": labels}))
    open_loan = "loan_id in self.results['get_loan'] and self.results['get_loan'][loan_id]['state'] == 'open'"
    assert open_loan in response.preconditions[EXTEND], response.preconditions
    assert open_loan in response.preconditions[SWAP]  # where the labels chose it
    lines = closed[0].program.splitlines()
    extend = next(k for k, line in enumerate(lines, 1) if ".extend_loan(" in line)
    verdict = engine.check(CheckRequest(spec=demos.spec, preconditions=response.preconditions,
                                        history="\n".join(lines[: extend - 1]) + "\n", calls=[lines[extend - 1]]))
    assert not verdict.results[0].allowed  # extending the closed loan: never labelled, refused all the same


def test_what_earlier_writes_show_of_a_field_the_read_holds_at_one_value_is_proposed_for_labels() -> None:
    converted = convert([desk_run(n) for n in range(6)], TOOLS, writes=WRITES)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    found = relations(facts, "extend_loan", spec.methods[EXTEND].positional)
    shown = ("all(self.changes[w][loan_id]['state'] == 'open' for w in ('extend_loan', 'swap_copies') "
             "if loan_id in self.changes[w])")
    assert shown in found and labels_only(shown)  # every loan the calls extend was read open
    rule = compile_rule(shown, Scope(AGENT_SHAPE, PARAMS["extend_loan"]))
    state = SimpleNamespace(results={}, changes={"swap_copies": {"L1": {"state": "closed"}, "L2": {"state": "open"}}},
                            errors={}, seen={}, last_ok=True, user=SimpleNamespace(messages=1, last_said="yes"))
    assert [rule(Frame(state, (loan,))) for loan in ("L1", "L2", "L3")] == [False, True, True]


def test_the_labelled_calls_of_every_action_are_judged_in_one_run_of_the_labelled_runs(engine: Engine) -> None:
    demos = convert([desk_run(n) for n in range(6)], TOOLS, writes=WRITES)
    closed = convert([desk_run(n, state="closed") for n in (8, 9)], TOOLS, writes=WRITES).trajectories
    lines = closed[0].program.splitlines()
    at = {name: next(k for k, line in enumerate(lines, 1) if f".{name}(" in line) for name in ("swap_copies",
                                                                                                "extend_loan")}
    labels = [{"program": t.program, "calls": [{"line": line, "verdict": "refuse", "name": f"{name} {t.name}"}
                                               for name, line in at.items()]} for t in closed]
    runs: list[int] = []
    evaluate = engine._sandbox.evaluate

    def counted(spec: str, programs: list[str], *args: object, **kwargs: object) -> object:
        runs.append(len(programs))
        return evaluate(spec, programs, *args, **kwargs)  # type: ignore[arg-type]

    engine._sandbox.evaluate = counted  # type: ignore[method-assign]
    try:
        response = engine.infer(InferRequest.model_validate({
            "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories],
            "actions": [SWAP, EXTEND], "options": {"generators": ["enumerate"]}, "counterexamples": labels}))
    finally:
        del engine._sandbox.evaluate
    assert runs.count(len(labels)) == 1, runs  # both actions' conditions at their labelled calls: one run
    open_loan = "loan_id in self.results['get_loan'] and self.results['get_loan'][loan_id]['state'] == 'open'"
    assert open_loan in response.preconditions[EXTEND] and open_loan in response.preconditions[SWAP]
