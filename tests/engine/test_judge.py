"""The code model as judge (precond.engine.judging.judge): what it may decide, and the engine asking it through a real
sandbox."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.judging import judge
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.schemas import InferRequest

NEUTRAL = "def check(self):\n    assert"


class ScriptedScorer:
    """Log-likelihoods by rule: `prefers` gets `best`, everything else -10; the neutral header gets `neutral`."""

    def __init__(self, prefers: str, best: float = 0.0, neutral: float = -5.0) -> None:
        self.prefers, self.best, self.neutral = prefers, best, neutral
        self.prompts: list[str] = []

    def score(self, prefix: str, continuations: Sequence[str]) -> list[float]:
        self.prompts.append(prefix)
        if "def check(self" in prefix.splitlines()[-2]:
            return [self.neutral for _ in continuations]
        return [self.best if text.strip() == self.prefers else -10.0 for text in continuations]


SPEC = parse_spec(
    "class A:\n    def __init__(self):\n        self.ready = False\n        self.done = False\n"
    "    def go(self):\n        pass\n    def stop(self):\n        pass\n"
    "    def set(self):\n        self.ready = True\n"
)
ACTIONS = ["A.go", "A.stop"]


def _ask(scorer: ScriptedScorer, open_: Sequence[str] = ("self.ready", "self.done")) -> judge.Verdict:
    question = judge.question("A.stop", "zero-shot", open_, ["not self.ready"])
    return judge.decide(scorer, SPEC, ACTIONS, "a = A()\na.go()\n", {"A.go": ["self.ready"]}, question)


def test_a_confident_choice_that_is_specific_to_the_action_is_adopted() -> None:
    verdict = _ask(ScriptedScorer("self.done"))
    assert verdict.adopted == "self.done"
    assert verdict.describe("self.done").startswith("kept by the code model's judgment")


@pytest.mark.parametrize("scorer", [
    ScriptedScorer("self.done", best=-9.0),  # leads by 1 nat: not confident
    ScriptedScorer("self.done", neutral=1.0),  # as likely for any method: copying, not judgment
    ScriptedScorer("not self.ready"),  # not one of the undecided options
])
def test_no_confident_judgment_leaves_the_evidence_answer(scorer: ScriptedScorer) -> None:
    verdict = _ask(scorer)
    assert verdict.adopted is None
    assert "not kept" in verdict.describe(scorer.prefers) or scorer.prefers == "not self.ready"


def test_the_prompt_shows_the_other_actions_established_rules_and_ends_in_the_asked_assert() -> None:
    scorer = ScriptedScorer("self.done")
    _ask(scorer)
    asked, neutral = scorer.prompts
    assert "def go(self):\n        assert self.ready\n    def stop(self):\n        assert" in asked
    assert asked.endswith("def stop(self):\n        assert") and neutral.endswith("def check(self):\n        assert")
    assert "a.go()" in asked  # the demonstration


def test_options_are_bounded_and_put_the_undecided_first() -> None:
    many = [f"self.x{i}" for i in range(50)]
    question = judge.question("A.stop", "phase", ["self.ready"], many)
    assert question.options[0] == "self.ready" and len(question.options) == judge.MAX_OPTIONS
    assert question.open == {"self.ready"}


@pytest.fixture(scope="module")
def sandbox() -> Iterator[Sandbox]:
    with Sandbox(workers=1) as box:
        yield box


def _without_goodbye(data: dict[str, Any]) -> list[str]:
    return ["\n".join(line for line in d["program"].splitlines() if "system.GOODBYE" not in line)
            for d in data["demos"]]


def _infer(sandbox: Sandbox, data: dict[str, Any], scorer: ScriptedScorer, judge_on: bool) -> Any:
    loader: Callable[[], Any] = lambda: scorer  # noqa: E731
    engine = Engine(sandbox, loader)
    return engine.infer(InferRequest(spec=data["spec_program"], demonstrations=_without_goodbye(data),
                                     options={"generators": ["enumerate"], "judge": judge_on, "unseen": "allow",
                                              "library": False, "candidates": "all"}))


def test_a_never_demonstrated_action_gets_the_rule_the_model_confidently_judges(
    sandbox: Sandbox, restaurants: dict[str, Any]
) -> None:
    scorer = ScriptedScorer("self.user.no_more")
    judged = _infer(sandbox, restaurants, scorer, judge_on=True)
    assert judged.preconditions["SYSTEM.GOODBYE"] == ["self.user.no_more"]
    [report] = [c for c in judged.candidates["SYSTEM.GOODBYE"] if c.assertion == "self.user.no_more"]
    assert report.kept and (report.reason or "").startswith("kept by the code model's judgment")
    assert "judge" in judged.stats.seconds

    plain = _infer(sandbox, restaurants, ScriptedScorer("self.user.no_more"), judge_on=False)
    assert plain.preconditions["SYSTEM.GOODBYE"] == []


def test_an_unsure_model_adds_nothing_and_says_so(sandbox: Sandbox, restaurants: dict[str, Any]) -> None:
    unsure = _infer(sandbox, restaurants, ScriptedScorer("self.user.no_more", best=-9.5), judge_on=True)
    assert unsure.preconditions["SYSTEM.GOODBYE"] == []
    [report] = [c for c in unsure.candidates["SYSTEM.GOODBYE"] if c.assertion == "self.user.no_more"]
    assert "not confidently" in (report.reason or "")
