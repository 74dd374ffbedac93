"""Relations between a tool call and what came before it (precond/engine/candidates/tool_relations.py), on a library
desk agent
written from scratch: an earlier write on the same loan, an argument among its values, an argument against a date
the read holds, the books of that loan, the loan's member as the one read and their card, and the user's "yes".
Every one is a condition the embedded guard runs; one it cannot run is never proposed."""

from __future__ import annotations

import ast
import json
from collections.abc import Iterator, Mapping
from types import SimpleNamespace

import pytest

from precond.convert.openai import convert
from precond.engine.candidates import tool_facts
from precond.engine.candidates.tool_relations import labels_only, relations, runnable
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import Frame, Scope, compile_rule
from precond_client.schemas import CheckRequest, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "array" if p == "book_ids" else "string"} for p in params}, "required": list(params)}}}
    for name, params in [("get_member", ("member_id",)), ("get_loan", ("loan_id",)), ("get_title", ("title_id",)),
                         ("renew_loan", ("loan_id", "book_ids", "card_id", "reason", "until")),
                         ("close_loan", ("loan_id",))]]
RENEW = "AGENT.renew_loan"
WRITES = {"renew_loan", "close_loan"}
LOAN = "self.results['get_loan'][loan_id]"
HAS = "loan_id in self.results['get_loan']"


def call(tool: str, arguments: Mapping[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": tool, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def desk_run(n: int, reason: str, renew_twice: bool = False, book: str | None = None) -> list[dict[str, object]]:
    """Member m{n} asks to renew loan L{n} (books b{n}a, b{n}b, due 2024-06-0{n % 9 + 1}) until a later date."""
    due = f"2024-06-0{n % 9 + 1}"
    loan = {"loan_id": f"L{n}", "member_id": f"m{n}", "due": due,
            "books": [{"book_id": f"b{n}a", "title_id": f"t{n}"}, {"book_id": f"b{n}b", "title_id": f"t{n}"}]}
    title = {"title_id": f"t{n}", "copies": {f"b{n}{c}": {"shelf": c} for c in "abc"}}
    renew = {"loan_id": f"L{n}", "book_ids": [book or f"b{n}a"], "card_id": f"card_{n}", "reason": reason,
             "until": f"2024-07-0{n % 9 + 1}"}
    steps: list[dict[str, object]] = [{"role": "user", "content": f"I am m{n}, renew my loan"},
             *call("get_member", {"member_id": f"m{n}"}, {"name": "x", "cards": {f"card_{n}": {"kind": "library"}}}),
             *call("get_loan", {"loan_id": f"L{n}"}, loan), *call("get_title", {"title_id": f"t{n}"}, title),
             {"role": "user", "content": "yes"},
             *call("renew_loan", renew, {"ok": True})]
    if renew_twice:
        steps += [{"role": "user", "content": "yes"}, *call("renew_loan", renew, {"ok": True})]
    return steps


REASONS = ("exam", "travel", "illness")


def relations_of(runs: list[list[dict[str, object]]]) -> list[str]:
    converted = convert(runs, TOOLS, writes=WRITES)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    return relations(facts, "renew_loan", spec.methods[RENEW].positional)


def test_each_relation_kind_is_proposed_from_what_the_demonstrated_calls_show() -> None:
    found = relations_of([desk_run(n, REASONS[n % 3]) for n in range(6)])
    assert "loan_id not in self.changes['renew_loan']" in found  # an earlier write on the same loan
    assert "loan_id in self.changes['close_loan']" in found  # another write on the same key
    assert "reason in ('exam', 'illness', 'travel')" in found  # an argument among its values
    assert f"{HAS} and until >= {LOAN}['due']" in found  # an argument against a date of the same loan
    assert f"{HAS} and all(x in [y['book_id'] for y in {LOAN}['books']] for x in book_ids)" in found
    member = f"{LOAN}['member_id'] in self.results['get_member']"
    assert f"{HAS} and {member}" in found  # a join of two reads: the loan's member is one read
    assert f"{HAS} and {member} and card_id in self.results['get_member'][{LOAN}['member_id']]['cards']" in found
    assert "self.user.last_said == 'yes'" in found
    assert len(found) <= 48


def test_an_action_never_requires_its_own_earlier_success_on_the_key() -> None:
    # "renew only a loan already renewed" refuses every loan's first renewal: no policy says it, so it is never
    # proposed, although the labels of each run's first renewal, refused for another reason, would fit it
    found = relations_of([desk_run(n, REASONS[n % 3]) for n in range(6)])
    assert "loan_id in self.changes['renew_loan']" not in found
    assert "loan_id not in self.changes['renew_loan']" in found


def test_a_relation_a_demonstrated_call_breaks_is_not_proposed() -> None:
    found = relations_of([desk_run(n, REASONS[n % 3]) for n in range(5)] + [desk_run(9, "exam", book="zz")])
    assert not any("for x in book_ids" in a for a in found)  # one renewal named a book not on its loan
    assert not any(a.startswith("reason in") for a in relations_of([desk_run(n, f"r{n}") for n in range(9)]))


def test_every_proposed_relation_runs_in_the_embedded_guard_and_others_are_never_proposed() -> None:
    found = relations_of([desk_run(n, REASONS[n % 3]) for n in range(6)])
    params = ("loan_id", "book_ids", "card_id", "reason", "until")
    state = SimpleNamespace(results={"get_loan": {"L1": {"member_id": "m1", "due": "2024-06-02", "books": [
        {"book_id": "b1a", "title_id": "t1"}]}}, "get_member": {"m1": {"cards": {"card_1": {}}}},
        "get_title": {"t1": {"copies": {"b1a": {}}}}}, changes={}, errors={}, seen={},
        last_ok=True, user=SimpleNamespace(messages=2, last_said="yes"))
    for atom in found:
        rule = compile_rule(atom, Scope(AGENT_SHAPE, params))
        frame = Frame(state, ("L1", ["b1a"], "card_1", "exam", "2024-07-02"))
        assert rule(frame) is not None
    assert runnable(["reason.strip() == 'exam'", "reason in ('exam',)"], params) == ["reason in ('exam',)"]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, None)


def test_labelled_second_renewals_learn_once_per_loan(engine: Engine) -> None:
    demos = convert([desk_run(n, REASONS[n % 3]) for n in range(6)], TOOLS, writes=WRITES)
    twice = convert([desk_run(n, REASONS[n % 3], renew_twice=True) for n in (6, 7)], TOOLS,
                    writes=WRITES).trajectories
    second = [k for k, line in enumerate(twice[0].program.splitlines(), 1) if ".renew_loan(" in line][-1]
    labels = [{"program": t.program, "calls": [{"line": second, "verdict": "refuse", "name": f"second {t.name}"}]}
              for t in twice]
    response = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [RENEW],
        "options": {"generators": ["enumerate"]}, "counterexamples": labels}))
    rules = response.preconditions[RENEW]
    assert any("not in self.changes['renew_loan']" in r for r in rules), rules
    lines = twice[0].program.splitlines()
    first = next(k for k, line in enumerate(lines, 1) if ".renew_loan(" in line)
    for line, allowed in ((first, True), (second, False)):
        verdict = engine.check(CheckRequest(spec=demos.spec, preconditions=response.preconditions,
                                            history="\n".join(lines[: line - 1]) + "\n", calls=[lines[line - 1]]))
        assert verdict.results[0].allowed is allowed, (line, verdict)


def test_an_earlier_write_is_chosen_only_to_separate_labelled_calls() -> None:
    assert labels_only("loan_id not in self.changes['renew_loan']") and labels_only("x in self.changes['close_loan']")
    assert not labels_only(f"{HAS} and {LOAN}['member_id'] in self.results['get_member']")
