"""More labels never give a weaker guard (precond/engine/judging/counterexamples.py): a labelled call left on the wrong
side
costs in the choice of the rule, a call labelled 'refuse' that nothing separates is reported and never makes the
rule drop the conditions that separate the others, and a rule made from the labels that refuses demonstrated calls
is a conflict a human decides (`assumed`, named in the warning), never silently established."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.counterexamples import _kept, _smallest, unseparable
from precond.engine.judging.ranking import Candidate, Cluster
from precond.engine.judging.report import Ranked
from precond.engine.judging.run_tasks import own_task
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
    for name, params in [("get_parcel", ("parcel_id",)), ("refund_parcel", ("parcel_id",))]]
REFUND = "AGENT.refund_parcel"
CALL_LINE = 6


def run(pid: str, state: str, insured: str) -> list[dict[str, object]]:
    """A parcel-service agent reads a parcel, then refunds it: lost parcels and insured ones are refunded."""
    result = f'{{"parcel_id": "{pid}", "state": "{state}", "insured": "{insured}"}}'
    return [{"role": "user", "content": "refund please"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_parcel",
                                                               "arguments": f'{{"parcel_id": "{pid}"}}'}}]},
            {"role": "tool", "content": result},
            {"role": "assistant", "tool_calls": [{"function": {"name": "refund_parcel",
                                                               "arguments": f'{{"parcel_id": "{pid}"}}'}}]},
            {"role": "tool", "content": "{}"}]


def test_a_label_left_allowed_costs_so_a_condition_that_refuses_some_is_kept() -> None:
    # bits 0-2 to allow, 3-5 to refuse: `status` holds at every call to allow and refuses 3 and 4; call 5 nothing
    # separates. Counting only the calls to allow refused, adding `status` cost a condition and gained nothing.
    truth = {"read": 0b111111, "status": 0b100111}
    required, terms = _smallest(truth, 0b000111, 0b111000)
    assert "status" in required or ("status",) in terms


def test_a_label_nothing_separates_does_not_drop_the_terms_that_separate_the_others() -> None:
    # bits 0-1 to allow, 2-4 to refuse: `a` allows 0, `b` allows 1, neither allows 2 or 3; both allow 4.
    truth = {"a": 0b10001, "b": 0b10010}
    assert unseparable(truth, 0b00011, 0b11100) == 0b10000
    assert _smallest(truth, 0b00011, 0b11100) == ([], [("a",), ("b",)])


def test_a_condition_that_separates_only_its_own_task_is_not_chosen() -> None:
    # bits 0-2 to allow (tasks a, b, c), 3-7 to refuse (tasks a, a, a, b, c): `only_a` refuses the three of task a
    # (a value only that task shows), `status` one call of each task
    tasks = ["a", "b", "c", "a", "a", "a", "b", "c"]
    truth = {"only_a": 0b11000111, "status": 0b00110111}
    assert own_task(0b00111000, 0b11111000, tasks) and not own_task(0b11001000, 0b11111000, tasks)
    required, terms = _smallest(truth, 0b111, 0b11111000)  # without the tasks it is part of the rule
    assert "only_a" in required or any("only_a" in t for t in terms)
    required, terms = _smallest(truth, 0b111, 0b11111000, tasks)
    assert "only_a" not in required and not any("only_a" in t for t in terms) and (required or terms)
    assert not own_task(0b00111000, 0b00111000 | 0b01000000, ["a"] * 3 + ["a", "a", "a", "b", "b"])  # 2 tasks


def test_a_condition_refusing_one_task_alone_of_every_call_labelled_refuse_is_not_chosen() -> None:
    # bits 0-2 to allow (tasks a, b, c), 3-6 to refuse (tasks a, a, b, c); the rules kept already refuse 5 and 6,
    # leaving task a's two. `only_a` refuses those alone, `reason` (two comparisons: dearer) refuses every call
    # labelled 'refuse': judged across every task's refused calls, only `reason` is one, although the calls left
    # are all one task's
    tasks = ["a", "b", "c", "a", "a", "b", "c"]
    truth = {"only_a": 0b1100111, "x == 1 and y == 2": 0b0000111}
    required, terms = _smallest(truth, 0b111, 0b0011000, tasks, 0b1111000)
    assert "only_a" not in required and not any("only_a" in t for t in terms)
    assert "x == 1 and y == 2" in required or ("x == 1 and y == 2",) in terms


def test_an_assumed_rule_no_label_contradicts_stays_with_labels() -> None:
    # bits 0-1 to allow, 2-3 to refuse: `owned` (assumed) holds at all four, `status` (established) refuses 2-3.
    # Without labels both are the guard; the labels refute neither, so neither is dropped (more labels never make
    # the guard weaker), while `wrong` (assumed), which refuses call 1 to allow, goes
    chosen = [Cluster((Candidate(e, "enumerate", 0b1),)) for e in ("owned", "status", "wrong")]
    ranked = Ranked(results=[], valid=[], clusters=chosen, chosen=chosen,
                    decided={"owned": "assumed", "status": "established", "wrong": "assumed"})
    kept, notes = _kept(ranked, {"owned": 0b1111, "status": 0b0011, "wrong": 0b1101}, 0b0011, 0b1100)
    assert kept == {"owned", "status"} and notes["wrong"].startswith("dropped")
    kept, _ = _kept(ranked, {"owned": 0b1111, "status": 0b0011, "wrong": 0b1101}, 0b0011, 0b1100, unshown=True)
    assert kept == {"status"}  # every demonstrated call labelled 'refuse': only what refuses them rests on them


DEMOS = convert([run("A1", "lost", "no"), run("B2", "delivered", "yes"), run("C3", "lost", "yes"),
                 run("D4", "delivered", "yes")], TOOLS)
REFUSED = convert([run("E5", "delivered", "no"), run("F6", "in_transit", "no")], TOOLS)
SAME_AS_ALLOWED = convert([run("G7", "lost", "yes")], TOOLS)
"""A call whose facts are those of calls to allow (the reason to refuse it is not in the log: a second refund)."""


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, None)


def labels(*runs: tuple[Any, str]) -> list[dict[str, object]]:
    return [{"program": t.program, "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": name}]}
            for t, name in runs]


def infer(engine: Engine, demos: Any, counterexamples: list[dict[str, object]]) -> Any:
    return engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [REFUND],
        "options": {"generators": ["enumerate"]}, "counterexamples": counterexamples}))


def refused(engine: Engine, rules: dict[str, list[str]], program: str) -> bool:
    lines = program.splitlines()
    return not engine.check(CheckRequest(spec=DEMOS.spec, preconditions=rules,
                                         history="\n".join(lines[: CALL_LINE - 1]) + "\n",
                                         calls=[lines[CALL_LINE - 1]])).results[0].allowed


def test_one_more_label_nothing_separates_keeps_the_rule_the_others_gave(engine: Engine) -> None:
    two = infer(engine, DEMOS, labels((REFUSED.trajectories[0], "E5"), (REFUSED.trajectories[1], "F6")))
    three = infer(engine, DEMOS, labels((REFUSED.trajectories[0], "E5"), (REFUSED.trajectories[1], "F6"),
                                        (SAME_AS_ALLOWED.trajectories[0], "G7 second refund")))
    for response in (two, three):
        assert all(refused(engine, response.preconditions, t.program) for t in REFUSED.trajectories)
        assert not any(refused(engine, response.preconditions, t.program) for t in DEMOS.trajectories)
    assert "G7 second refund" in three.warnings[REFUND] and "unseparated" in three.warnings[REFUND]


def test_a_rule_from_labels_that_refuses_a_demonstrated_call_is_a_conflict_for_a_human(engine: Engine) -> None:
    # X9 is demonstrated delivered and uninsured, as three calls labelled 'refuse' are: nothing tells them apart,
    # and refusing the one demonstrated call costs less than allowing the three
    demos = convert([*(run(p, s, i) for p, s, i in (("A1", "lost", "no"), ("B2", "delivered", "yes"),
                                                    ("C3", "lost", "yes"), ("D4", "delivered", "yes"))),
                     run("X9", "delivered", "no")], TOOLS)
    names = ("E5", "E6", "E7")
    twins = convert([run(p, "delivered", "no") for p in names], TOOLS).trajectories
    response = infer(engine, demos, labels(*zip(twins, names, strict=True),
                                           (REFUSED.trajectories[1], "F6")))
    rules = response.preconditions[REFUND]
    conflicted = [r for r in rules if response.evidence[REFUND][r].refuses_allowed]
    assert conflicted, rules
    assert all(response.evidence[REFUND][r].decided == "assumed" for r in conflicted)
    warning = response.warnings[REFUND]
    assert "conflict" in warning and "a demonstrated call" in warning and "E6" in warning
