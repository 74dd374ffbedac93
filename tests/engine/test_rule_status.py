"""Every verdict of a check says what the rule of the action it judged rests on (`rule_status`), so that "allowed
because the evidence says so" reads differently from "allowed because nothing is known"; and a never-demonstrated
action gets the code model's zero-shot guess, whatever `options.unseen` says, and the rule `False` (refused) only
when there is no guess. A small card-blocking domain: every action but REPORT_FRAUD is demonstrated four times."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.judging.report import UNSEEN_RULE
from precond.sandbox import Sandbox
from precond_client.schemas import (
    CheckRequest,
    InferOptions,
    InferRequest,
    InferResponse,
    ModelInfo,
    PriorSource,
    rule_status,
)
from tests.engine.test_cautious import CARD_SPEC as SPEC  # the card-blocking domain of the cautious tests

DEMOS = ["\n".join([
    "user = USER()", "system = SYSTEM(user)", "user.INFORM_INTENT('block_card')",
    f"system.REQUEST({first!r})", f"user.INFORM({first!r})", f"system.REQUEST({second!r})",
    f"user.INFORM({second!r})", "system.VERIFY_IDENTITY()", "system.identity_result(True)",
    "system.CONFIRM()", "user.AFFIRM()", "system.BLOCK_CARD()", "system.block_result(True)", "system.NOTIFY()",
]) + "\n" for first, second in (("name", "dob"), ("dob", "name")) * 2]
HISTORY = [{"actor": "user", "act": "INFORM_INTENT", "args": ["block_card"]},
           {"actor": "user", "act": "INFORM", "args": ["name"]}, {"actor": "user", "act": "INFORM", "args": ["dob"]},
           {"actor": "system", "act": "VERIFY_IDENTITY", "args": []},
           {"actor": "system", "act": "identity_result", "args": [True]}]
GUESS = "self.identity_verified"


class GuessingModel:
    """The code model, answering every prompt with `assert <guess>` (a rule several samples agree on), or with
    text that is no assertion (no guess)."""

    info = ModelInfo(name="guessing", device="cpu", dtype="none")
    known_calls: tuple[str, ...] = ()

    def __init__(self, guess: str | None) -> None:
        self.guess = guess

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        return [[f" {self.guess}" if self.guess else " ((("] * n for _ in suffixes]


@pytest.fixture(scope="module")
def sandbox() -> Iterator[Sandbox]:
    with Sandbox(workers=2) as running:
        yield running


def _infer(engine: Engine, **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=DEMOS, options=InferOptions(**options)))


def _labels(response: InferResponse) -> dict[str, dict[str, str]]:
    return {a: {rule: e.decided or "" for rule, e in rules.items()} for a, rules in response.evidence.items()}


def _statuses(engine: Engine, rules: dict[str, list[str]], decided: dict[str, dict[str, str]]) -> dict[str, Any]:
    calls = ["system.CONFIRM()", "system.BLOCK_CARD()", "system.REPORT_FRAUD()", "system.NOTIFY()"]
    verdicts = engine.check(CheckRequest(spec=SPEC, preconditions=rules, decided=decided, history=HISTORY,
                                         calls=calls)).results
    assert [v.action for v in verdicts] == ["SYSTEM.CONFIRM", "SYSTEM.BLOCK_CARD", "SYSTEM.REPORT_FRAUD",
                                            "SYSTEM.NOTIFY"]
    return {v.action: (v.rule_status, v.allowed) for v in verdicts}


def test_each_verdict_says_what_its_rule_rests_on(sandbox: Sandbox) -> None:
    engine = Engine(sandbox, None)
    inferred = _infer(engine, generators=["enumerate"])
    assert inferred.evidence["SYSTEM.BLOCK_CARD"][GUESS].decided == "assumed"
    statuses = _statuses(engine, inferred.preconditions, _labels(inferred))
    assert statuses["SYSTEM.CONFIRM"][0] == "established"
    assert statuses["SYSTEM.BLOCK_CARD"][0] == "assumed"  # the weakest of its rules
    assert statuses["SYSTEM.REPORT_FRAUD"] == ("missing", False)  # never demonstrated: `False`, refused
    # the same rules without a word on how they were decided: given, and an action without rules is missing
    rules = {a: r for a, r in inferred.preconditions.items() if a != "SYSTEM.NOTIFY"}
    plain = _statuses(engine, rules, {})
    assert plain["SYSTEM.CONFIRM"][0] == plain["SYSTEM.BLOCK_CARD"][0] == "given"
    assert plain["SYSTEM.NOTIFY"] == ("missing", True)  # allowed because nothing is known, and it says so


def test_allowing_an_unseen_action_says_nothing_is_known(sandbox: Sandbox) -> None:
    engine = Engine(sandbox, None)
    allowing = _infer(engine, generators=["enumerate"], unseen="allow")
    assert allowing.preconditions["SYSTEM.REPORT_FRAUD"] == []
    assert _statuses(engine, allowing.preconditions, _labels(allowing))["SYSTEM.REPORT_FRAUD"] == ("missing", True)


def test_a_prior_rule_is_transferred(sandbox: Sandbox) -> None:
    engine = Engine(sandbox, None)
    prior = PriorSource(source="another service", rules={"SYSTEM.REPORT_FRAUD": [GUESS]})
    inferred = _infer(engine, generators=["enumerate"], prior_sources=[prior])
    assert inferred.preconditions["SYSTEM.REPORT_FRAUD"] == [GUESS]
    statuses = _statuses(engine, inferred.preconditions, _labels(inferred))
    assert statuses["SYSTEM.REPORT_FRAUD"] == ("transferred", True)


def test_a_never_demonstrated_action_gets_the_models_guess_under_the_default_and_says_so(sandbox: Sandbox) -> None:
    """`options.unseen: "refuse"` (the default) decides only what the model left open: a guess several samples
    agree on is the rule (`zero-shot`, in the evidence, the warning and every verdict); without one, `False`."""
    assert InferOptions().unseen == "refuse"
    guessed = _infer(Engine(sandbox, lambda: GuessingModel(GUESS)))  # type: ignore[arg-type,return-value]
    assert guessed.preconditions["SYSTEM.REPORT_FRAUD"] == [GUESS]
    assert guessed.evidence["SYSTEM.REPORT_FRAUD"][GUESS].decided == "zero-shot"
    assert "zero-shot guess" in guessed.warnings["SYSTEM.REPORT_FRAUD"]
    engine = Engine(sandbox, None)
    assert _statuses(engine, guessed.preconditions, _labels(guessed))["SYSTEM.REPORT_FRAUD"] == ("zero-shot", True)
    unsure = _infer(Engine(sandbox, lambda: GuessingModel(None)))  # type: ignore[arg-type,return-value]
    assert unsure.preconditions["SYSTEM.REPORT_FRAUD"] == [UNSEEN_RULE]
    assert "refused" in unsure.warnings["SYSTEM.REPORT_FRAUD"]
    assert _statuses(engine, unsure.preconditions, _labels(unsure))["SYSTEM.REPORT_FRAUD"] == ("missing", False)
    described = InferOptions.model_fields["unseen"].description or ""
    assert "zero-shot guess" in described and described.index("guess") < described.index("'refuse'")


@pytest.mark.parametrize(("rules", "labels", "status"), [
    ("ab", {"a": "established", "b": "established"}, "established"),
    ("ab", {"a": "established", "b": "assumed"}, "assumed"),
    ("ab", {"a": "assumed", "b": "transferred"}, "transferred"),
    ("ab", {"a": "zero-shot", "b": "transferred"}, "zero-shot"),
    ("a", {"a": "unseen"}, "missing"),
    ("ab", {"a": "established", "b": "no evidence"}, "given"),
    ("ab", {"a": "established"}, "given"),  # b is not labelled
    ("", {"a": "established"}, "missing"),
])
def test_an_actions_status_is_its_weakest_rules(rules: str, labels: dict[str, str], status: str) -> None:
    assert rule_status(list(rules), labels) == status
