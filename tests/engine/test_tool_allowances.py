"""Allowances over a tool call's integer arguments (precond/engine/candidates/tool_conditions.py `allowances`):
proposed only
for actions whose calls carry two integers and a list, chosen only to refuse calls labelled 'refuse' that nothing
else refuses (precond/engine/judging/counterexamples.py), never kept from demonstrations alone."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest

TYPES = {"passengers": "array", "payment_methods": "array", "total_baggages": "integer",
         "nonfree_baggages": "integer"}
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": TYPES.get(p, "string")} for p in params}, "required": list(params)}}}
    for name, params in [("get_user_details", ("user_id",)), ("send_note", ("user_id",)),
                         ("book_reservation", ("user_id", "passengers", "payment_methods", "total_baggages",
                                               "nonfree_baggages"))]]
BOOK = "AGENT.book_reservation"
USER = "mia_1"
CALL_LINE = 6
"""The booking's line (1-based) in each run's program."""
ALLOWANCE = "nonfree_baggages == max(0, total_baggages - 3 * len(passengers))"


def booking(total: int, nonfree: int, paid: tuple[str, ...] = ("credit_card_1",)
            ) -> list[dict[str, object]]:
    profile = f'{{"user_id": "{USER}", "membership": "gold", "payment_methods": {{}}}}'
    methods = ", ".join(f'{{"payment_id": "{p}"}}' for p in paid)
    arguments = (f'{{"user_id": "{USER}", "passengers": [{{"first_name": "A"}}], "payment_methods": [{methods}], '
                 f'"total_baggages": {total}, "nonfree_baggages": {nonfree}}}')
    return [{"role": "user", "content": "please book"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_user_details",
                                                               "arguments": f'{{"user_id": "{USER}"}}'}}]},
            {"role": "tool", "content": profile},
            {"role": "assistant", "tool_calls": [{"function": {"name": "book_reservation", "arguments": arguments}}]},
            {"role": "tool", "content": "{}"}]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def labels(runs: list[tuple[list[dict[str, object]], str]]) -> tuple[Any, list[dict[str, Any]]]:
    converted = convert([r for r, _ in runs], TOOLS)
    return converted, [{"program": t.program, "calls": [{"line": CALL_LINE, "verdict": verdict, "name": t.name}]}
                       for t, (_, verdict) in zip(converted.trajectories, runs, strict=True)]


def infer(engine: Engine, demos: Any, counterexamples: list[dict[str, Any]]) -> Any:
    return engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [BOOK],
        "options": {"generators": ["enumerate"]}, "counterexamples": counterexamples}))


def test_the_allowance_labelled_calls_break_tightens_the_rule_and_judges_new_bookings(engine: Engine) -> None:
    """Two certificates are refused by the certificate limit; of the bookings it leaves, bags charged while the
    allowance is left (3 with 1 charged) and free bags beyond it (6 with none charged) are refused, and 2 free, and
    5 with 2 charged, allowed: only an allowance of 3 per passenger separates them, added beside the limit."""
    demos = convert([booking(0, 0), booking(1, 0), booking(2, 0)], TOOLS)
    converted, counterexamples = labels([(booking(0, 0, ("certificate_1", "certificate_2")), "refuse"),
                                 (booking(3, 1), "refuse"), (booking(6, 0), "refuse"),
                                 (booking(2, 0), "allow"), (booking(5, 2), "allow")])
    names = [t.name for t in converted.trajectories]
    inferred = infer(engine, demos, counterexamples)
    assert ALLOWANCE in inferred.preconditions[BOOK]
    assert sorted(inferred.evidence[BOOK][ALLOWANCE].refuses) == sorted(names[1:3])
    lines = convert([booking(4, 1)], TOOLS).trajectories[0].program.splitlines()
    verdicts = engine.check(CheckRequest(spec=demos.spec, preconditions=inferred.preconditions,
                                         history="\n".join(lines[: CALL_LINE - 1]) + "\n",
                                         calls=[lines[CALL_LINE - 1],
                                                lines[CALL_LINE - 1].replace("4, 1)", "4, 0)")])).results
    assert [v.allowed for v in verdicts] == [True, False]


def test_an_allowance_alone_never_opens_an_action_nothing_else_separates(engine: Engine) -> None:
    """Never demonstrated, and only the bag counts tell the labelled bookings apart: the action stays refused
    (`options.unseen`) rather than allowed wherever the counts fit."""
    note = {"role": "assistant", "tool_calls": [{"function": {"name": "send_note",
                                                              "arguments": f'{{"user_id": "{USER}"}}'}}]}
    demos = convert([[*booking(0, 0)[:3], note, {"role": "tool", "content": "{}"}]] * 3, TOOLS)
    _, counterexamples = labels([(booking(3, 1), "refuse"), (booking(6, 0), "refuse"),
                                 (booking(2, 0), "allow"), (booking(5, 2), "allow")])
    inferred = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories],
        "actions": [BOOK, "AGENT.send_note"], "options": {"generators": ["enumerate"]},
        "counterexamples": counterexamples}))
    assert inferred.preconditions[BOOK] == ["False"]


def test_an_allowance_never_replaces_a_condition_that_already_separates(engine: Engine) -> None:
    """The refused bookings pay with two certificates; the bag counts happen to differ from the allowed ones too,
    but the certificate limit already refuses them, so no allowance is added."""
    demos = convert([booking(0, 0), booking(1, 0), booking(2, 0)], TOOLS)
    two = ("certificate_1", "certificate_2")
    _, counterexamples = labels([(booking(3, 1, two), "refuse"), (booking(6, 0, two), "refuse"),
                                 (booking(2, 0), "allow"), (booking(5, 2), "allow")])
    inferred = infer(engine, demos, counterexamples)
    assert not any("max(0, " in rule for rule in inferred.preconditions[BOOK])


def test_an_allowance_every_demonstration_meets_is_not_kept_without_labels(engine: Engine) -> None:
    demos = convert([booking(2, 0), booking(5, 2), booking(0, 0)], TOOLS)
    inferred = infer(engine, demos, [])
    assert not any("max(0, " in rule for rule in inferred.preconditions[BOOK])
