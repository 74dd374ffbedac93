"""Labelled calls in an infer request (precond/engine/judging/counterexamples.py): a demonstrated call labelled 'refuse'
is evidence against a rule, a run's labelled calls join the evidence, the rules separate the two sides and say
which labelled calls they refuse; labels that name nothing, or contradict each other, are a 422."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.counterexamples import _terms, _text
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest, ModelInfo
from precond_client.schemas.errors import InvalidInput

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
    for name, params in [("get_reservation_details", ("reservation_id",)), ("cancel_reservation", ("reservation_id",))]]
CANCEL = "AGENT.cancel_reservation"


def run(rid: str, cabin: str, insured: str) -> list[dict[str, object]]:
    result = f'{{"reservation_id": "{rid}", "cabin": "{cabin}", "insurance": "{insured}"}}'
    return [{"role": "user", "content": "please cancel"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_reservation_details",
                                                               "arguments": f'{{"reservation_id": "{rid}"}}'}}]},
            {"role": "tool", "content": result},
            {"role": "assistant", "tool_calls": [{"function": {"name": "cancel_reservation",
                                                               "arguments": f'{{"reservation_id": "{rid}"}}'}}]},
            {"role": "tool", "content": "{}"}]


DEMOS = convert([run("A1", "business", "no"), run("B2", "economy", "yes"), run("C3", "basic_economy", "no"),
                 run("D4", "business", "yes"), run("G7", "economy", "yes")], TOOLS)
OTHERS = convert([run("E5", "basic_economy", "no"), run("F6", "economy", "no"), run("H8", "business", "no")], TOOLS)
CALL_LINE = 6
"""The cancellation's line (1-based) in each run's program."""


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def request(counterexamples: list[dict[str, Any]]) -> InferRequest:
    return InferRequest.model_validate({
        "spec": DEMOS.spec, "demonstrations": [t.program for t in DEMOS.trajectories], "actions": [CANCEL],
        "options": {"generators": ["enumerate"]}, "counterexamples": counterexamples})


LABELS = [{"demonstration": 2, "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": "C3 basic economy"}]},
          {"program": OTHERS.trajectories[0].program,
           "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": "E5 basic economy"}]},
          {"program": OTHERS.trajectories[1].program,
           "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": "F6 economy uninsured"}]},
          {"program": OTHERS.trajectories[2].program,
           "calls": [{"line": CALL_LINE, "verdict": "allow", "name": "H8 business"}]}]


def allowed(engine: Engine, rules: dict[str, list[str]], program: str) -> bool:
    lines = program.splitlines()
    verdict = engine.check(CheckRequest(spec=DEMOS.spec, preconditions=rules,
                                        history="\n".join(lines[: CALL_LINE - 1]) + "\n",
                                        calls=[lines[CALL_LINE - 1]]))
    return verdict.results[0].allowed


def test_labelled_calls_choose_the_rule_that_separates_them(engine: Engine) -> None:
    plain = engine.infer(request([]))
    assert allowed(engine, plain.preconditions, OTHERS.trajectories[0].program)  # the demonstrations allow it
    labelled = engine.infer(request(LABELS))
    rules = labelled.preconditions
    for refused in (DEMOS.trajectories[2], *OTHERS.trajectories[:2]):
        assert not allowed(engine, rules, refused.program), refused.name
    for kept in (*DEMOS.trajectories[:2], *DEMOS.trajectories[3:], OTHERS.trajectories[2]):
        assert allowed(engine, rules, kept.program), kept.name
    refuses = {name for rule in rules[CANCEL] for name in labelled.evidence[CANCEL][rule].refuses}
    assert refuses == {"C3 basic economy", "E5 basic economy", "F6 economy uninsured"}
    assert not any(labelled.evidence[CANCEL][rule].refuses_allowed for rule in rules[CANCEL])
    assert all(len(rule) < 300 for rule in rules[CANCEL])  # a few conditions, not a list of the calls


def test_a_label_that_names_no_call_or_contradicts_another_is_refused(engine: Engine) -> None:
    with pytest.raises(InvalidInput) as caught:
        engine.infer(request([{"demonstration": 0, "calls": [{"line": 3, "verdict": "refuse"}]}]))
    assert caught.value.field == "counterexamples[0].calls[0].line"
    with pytest.raises(InvalidInput) as caught:
        engine.infer(request([{"demonstration": 9, "calls": [{"line": CALL_LINE, "verdict": "refuse"}]}]))
    assert caught.value.field == "counterexamples[0].demonstration"
    same = OTHERS.trajectories[0].program
    with pytest.raises(InvalidInput) as caught:
        engine.infer(request([{"program": same, "calls": [{"line": CALL_LINE, "verdict": "refuse"}]},
                              {"program": same, "calls": [{"line": CALL_LINE, "verdict": "allow"}]}]))
    assert caught.value.field == "counterexamples[1].calls[0]" and "counterexamples[0].calls[0]" in str(caught.value)


def test_terms_cover_the_calls_to_allow_with_as_few_conditions_as_separate_them() -> None:
    # examples: bits 0-2 to allow, bits 3-4 to refuse
    truth = {"a": 0b00011, "b": 0b00100, "c": 0b11111, "d": 0b01111, "e": 0b10100}
    assert _terms(truth, 0b00111, 0b11000) == [("a",), ("b",)]
    assert _text([("a",), ("b",)]) == "a or b"
    assert _terms({"d": 0b01111, "e": 0b10100}, 0b00111, 0b11000) == [("d", "e")]
    assert _text([("x or y", "z")]) == "(x or y) and z"
    assert _terms({"c": 0b11111}, 0b00111, 0b11000) == []  # nothing separates: no rule is made up


def test_a_tie_goes_to_the_condition_that_holds_at_more_calls_to_allow() -> None:
    # bits 0-3 to allow, 4-5 to refuse: insured (0, 1), one way (0, 1, 2), nothing flown (0-3); the insured
    # call 4 has flown, call 5 is one way and uninsured. Both pairs allow 0 and 1 and refuse 4 and 5.
    truth = {"insured": 0b010011, "one_way": 0b100111, "nothing_flown": 0b101111, "recent": 0b001100}
    assert _terms(truth, 0b001111, 0b110000) == [("recent",), ("nothing_flown", "insured")]


class GuessingModel:
    """The code model, answering every prompt with `assert <guess>` (several samples agree: a zero-shot rule)."""

    info = ModelInfo(name="guessing", device="cpu", dtype="none")
    known_calls: tuple[str, ...] = ()

    def __init__(self, guess: str) -> None:
        self.guess = guess

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        return [[f" {self.guess}"] * n for _ in suffixes]


@pytest.mark.parametrize(("guess", "kept"), [("self.reservation.cabin == 'business'", False),
                                             ("self.user.messages > 0", True)])
def test_a_zero_shot_guess_that_raises_on_the_state_is_dropped_and_reported(guess: str, kept: bool) -> None:
    """`send_certificate` is never called: a guess over an attribute AGENT lacks would refuse every call with an
    error; it is rejected with the reason, the warning names it, and the action keeps `options.unseen`."""
    tools = [*TOOLS, {"type": "function", "function": {"name": "send_certificate", "parameters": {
        "properties": {"user_id": {"type": "string"}}, "required": ["user_id"]}}}]
    converted = convert([run("A1", "business", "no"), run("B2", "economy", "yes"), run("D4", "business", "yes")],
                        tools)
    model: Any = GuessingModel(guess)
    with Sandbox(workers=1) as sandbox:
        response = Engine(sandbox, lambda: model).infer(InferRequest.model_validate({
            "spec": converted.spec, "demonstrations": [t.program for t in converted.trajectories],
            "actions": ["AGENT.send_certificate", CANCEL], "options": {"judge": False, "candidates": "all"}}))
    rules = response.preconditions["AGENT.send_certificate"]
    assert rules == ([guess] if kept else ["False"])
    if not kept:
        report = next(c for c in response.candidates["AGENT.send_certificate"] if c.assertion == guess)
        assert not report.kept and "raises on the spec's state (AGENT has no attribute 'reservation')" in report.reason
        assert "AGENT has no attribute 'reservation'" in response.warnings["AGENT.send_certificate"]


BOOK_TOOLS = [*TOOLS, *[{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "array" if p == "payment_methods" else "string"} for p in params},
    "required": list(params)}}}
    for name, params in [("get_user_details", ("user_id",)), ("book_reservation", ("user_id", "payment_methods"))]]]
BOOK = "AGENT.book_reservation"


def booking(user: str, paid: Sequence[str], membership: str = "gold", amount: int = 50) -> list[dict[str, object]]:
    profile = f'{{"user_id": "{user}", "membership": "{membership}", ' \
              f'"payment_methods": {{{", ".join(f"{chr(34)}{p}{chr(34)}: {{}}" for p in paid)}}}}}'
    methods = ", ".join(f'{{"payment_id": "{p}", "amount": {amount}}}' for p in paid)
    return [{"role": "user", "content": "please book"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_user_details",
                                                               "arguments": f'{{"user_id": "{user}"}}'}}]},
            {"role": "tool", "content": profile},
            {"role": "assistant", "tool_calls": [{"function": {"name": "book_reservation", "arguments":
                                                               f'{{"user_id": "{user}", "payment_methods": '
                                                               f'[{methods}]}}'}}]},
            {"role": "tool", "content": "{}"}]


def test_an_action_never_demonstrated_learns_the_limit_its_refused_calls_break(engine: Engine) -> None:
    """Only calls labelled 'refuse' and no demonstration: the rule is the limit some of them break (at most one
    certificate), not `False`; a refused call no limit explains stays allowed and the warning names it."""
    demos = convert([run("A1", "business", "no"), run("B2", "economy", "yes"), run("D4", "business", "yes")],
                    BOOK_TOOLS)
    refused = convert([booking("u1", ["certificate_1", "certificate_2"]),
                       booking("u2", ["certificate_3", "certificate_4", "credit_card_5"]),
                       booking("u3", ["certificate_6", "certificate_7", "certificate_8"]),
                       booking("u4", ["certificate_9"])], BOOK_TOOLS)
    labels = [{"program": t.program, "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": t.name}]}
              for t in refused.trajectories]
    inferred = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [CANCEL, BOOK],
        "options": {"generators": ["enumerate"]}, "counterexamples": labels}))
    limit = "len([x for x in payment_methods if 'certificate_' in x['payment_id']]) <= 1"
    assert inferred.preconditions[BOOK] == [limit]
    assert sorted(inferred.evidence[BOOK][limit].refuses) == sorted(t.name for t in refused.trajectories[:3])
    assert inferred.evidence[BOOK][limit].decided == "established"
    assert f"unseparated: 1 call(s) labelled 'refuse' ({refused.trajectories[3].name})" in inferred.warnings[BOOK]
    one = convert([booking("u9", ["certificate_1", "credit_card_2"], "silver")], BOOK_TOOLS).trajectories[0].program
    lines = one.splitlines()
    verdicts = engine.check(CheckRequest(spec=demos.spec, preconditions=inferred.preconditions,
                                         history="\n".join(lines[: CALL_LINE - 1]) + "\n",
                                         calls=[lines[CALL_LINE - 1], lines[CALL_LINE - 1].replace(
                                             "credit_card_2", "certificate_2")])).results
    assert [v.allowed for v in verdicts] == [True, False]


def test_an_action_never_demonstrated_whose_labelled_calls_nothing_separates_stays_refused(engine: Engine) -> None:
    """Calls labelled both ways that no condition separates: the placeholder `False` (options.unseen), its
    status 'unseen', and a warning that says the labels could not be separated."""
    demos = convert([run("A1", "business", "no"), run("B2", "economy", "yes"), run("D4", "business", "yes")],
                    BOOK_TOOLS)
    both = convert([booking("u1", ["certificate_1"]), booking("u1", ["certificate_1"], amount=60)], BOOK_TOOLS)
    labels = [{"program": t.program, "calls": [{"line": CALL_LINE, "verdict": verdict, "name": t.name}]}
              for t, verdict in zip(both.trajectories, ("allow", "refuse"), strict=True)]
    inferred = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [CANCEL, BOOK],
        "options": {"generators": ["enumerate"]}, "counterexamples": labels}))
    assert inferred.preconditions[BOOK] == ["False"]
    assert inferred.evidence[BOOK]["False"].decided == "unseen"
    assert "unseparated: 1 call(s) labelled 'refuse'" in inferred.warnings[BOOK]
    assert "stays refused (options.unseen: 'refuse')" in inferred.warnings[BOOK]


def test_rules_resting_only_on_demonstrated_calls_labelled_refuse_are_not_kept(engine: Engine) -> None:
    """Every demonstrated call labelled 'refuse' and none 'allow': the demonstrations are evidence against the
    rules they show, not for, so the action is refused as a never-demonstrated one is (`options.unseen`)."""
    labels = [{"demonstration": k, "calls": [{"line": CALL_LINE, "verdict": "refuse", "name": f"demo {k}"}]}
              for k in range(len(DEMOS.trajectories))]
    assert engine.infer(request([])).preconditions[CANCEL] != ["False"]
    inferred = engine.infer(request(labels))
    assert inferred.preconditions[CANCEL] == ["False"]
    assert inferred.evidence[CANCEL]["False"].decided == "unseen"
    assert "stays refused (options.unseen: 'refuse')" in inferred.warnings[CANCEL]


DIALOG_SPEC = """class USER:
  def __init__(self):
    self.confirmed = False
  def confirm(self):
    self.confirmed = True
class SYSTEM:
  def __init__(self, user):
    self.user = user
  def greet(self):
    pass
  def book(self):
    pass
"""


def test_without_a_tool_spec_calls_to_refuse_alone_give_no_rule(engine: Engine) -> None:
    """The limits learned from calls to refuse alone are a tool spec's (counts, reads, dates); over a dialog's
    state any condition one refused call meets and another breaks would do, so the action stays refused."""
    start = "user = USER()\nsystem = SYSTEM(user)\n"
    runs = [start + "system.book()\n", start + "user.confirm()\nsystem.book()\n"]
    labels = [{"program": p, "calls": [{"line": len(p.splitlines()), "verdict": "refuse"}]} for p in runs]
    inferred = engine.infer(InferRequest.model_validate({
        "spec": DIALOG_SPEC, "demonstrations": [start + "system.greet()\n"] * 3,
        "actions": ["SYSTEM.greet", "SYSTEM.book"], "options": {"generators": ["enumerate"]},
        "counterexamples": labels}))
    assert inferred.preconditions["SYSTEM.book"] == ["False"]
