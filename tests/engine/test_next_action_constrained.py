"""Mode 'constrained' through the real sandbox with the tiny model: the allowed set, the choice, nothing allowed,
and the answers to bad input (the history, the action names)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from precond.engine.acting import constrained
from precond.engine.engine import Engine
from precond.engine.models import CodeModel, ModelSettings, load_code_model
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, NextActionOptions, NextActionRequest
from precond_client.schemas.errors import InvalidInput, UnknownAction

HISTORY = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\nuser.INFORM('city')\n"


@pytest.fixture(scope="module")
def tiny(tiny_model_dir: Path) -> CodeModel:
    return load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", max_batch=8))


@pytest.fixture(scope="module")
def engine(tiny: CodeModel) -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, lambda: tiny)


def _gt(data: dict[str, Any]) -> dict[str, list[str]]:
    return {f"SYSTEM.{a}": list(asserts) for a, asserts in data["gt_preconditions"].items()}


def _request(data: dict[str, Any], preconditions: dict[str, list[str]] | None = None, history: Any = HISTORY,
             **options: Any) -> NextActionRequest:
    return NextActionRequest(
        spec=data["spec_program"], preconditions=_gt(data) if preconditions is None else preconditions,
        demonstrations=[data["demos"][0]["program"]], history=history,
        options={"mode": "constrained", "return_allowed": True, **options},
    )


def test_the_allowed_set_is_what_the_sandbox_allows_and_the_call_is_chosen_from_it(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    [action] = engine.next_action(_request(restaurants, choose_by="line")).actions
    allowed = [a.call for a in action.allowed or []]
    judged = allowed + [r.call for r in action.rejected]
    assert action.attempts == len(judged) == len(set(judged))
    # every call judged, judged again by /check-actions' path: allowed exactly when listed as allowed
    verdicts = engine.check(CheckRequest(spec=restaurants["spec_program"], preconditions=_gt(restaurants),
                                         history=HISTORY, calls=judged[:64])).results
    assert [v.allowed for v in verdicts] == [c in allowed for c in judged[:64]]
    assert "system.REQUEST('cuisine')" in allowed and "system.REQUEST('city')" not in allowed
    refused = {r.call: r for r in action.rejected}
    assert refused["system.REQUEST('city')"].violations == ["not self.user.informed_slot[slot]"]
    assert refused["system.FindRestaurants()"].violations == ["self.user.informed_slot['cuisine']"]
    assert action.verified and action.call in allowed
    assert action.held == _gt(restaurants)[_action_of(action.call)]
    assert all(a.score is not None and a.score < 0 for a in action.allowed or [])  # every line, one pass
    best = max(action.allowed or [], key=lambda a: a.score or 0.0)
    assert action.call == best.call


def test_by_default_the_action_is_chosen_first_then_its_arguments(engine: Engine, restaurants: dict[str, Any]
                                                                  ) -> None:
    """`choose_by: action`: the last pass scores only the chosen action's allowed calls (its arguments)."""
    [action] = engine.next_action(_request(restaurants)).actions
    assert action.verified and action.call in {a.call for a in action.allowed or []}
    scored = [a for a in action.allowed or [] if a.score is not None]
    assert all(_action_of(a.call) == _action_of(action.call) for a in scored)
    if len(scored) > 1:
        assert action.call == max(scored, key=lambda a: a.score or 0.0).call


def _action_of(call: str) -> str:
    return "SYSTEM." + call.split(".", 1)[1].split("(", 1)[0]


def test_preconditions_that_allow_nothing_say_so(engine: Engine, restaurants: dict[str, Any]) -> None:
    nothing = {f"SYSTEM.{a}": ["False"] for a in restaurants["system_actions"]}
    [action] = engine.next_action(_request(restaurants, nothing, max_actions=3)).actions
    assert action.nothing_allowed and action.call is None and not action.verified
    assert action.allowed == [] and action.reason and action.reason.startswith("nothing allowed")
    assert action.rejected and all(r.violations == ["False"] for r in action.rejected)


def test_each_judged_call_says_what_the_rule_of_its_action_rests_on(engine: Engine, restaurants: dict[str, Any]
                                                                    ) -> None:
    """A chosen or refused call says, as a verdict of `check-actions` does, whether its action's rule is
    established, assumed, given or missing: a call allowed because nothing is known about its action says so."""
    rules = _gt(restaurants)
    request = _request(restaurants, {"SYSTEM.REQUEST": rules["SYSTEM.REQUEST"]}, choose_by="line").model_copy(
        update={"decided": {"SYSTEM.REQUEST": {r: "assumed" for r in rules["SYSTEM.REQUEST"]}}})
    [action] = engine.next_action(request).actions
    refused = {r.call: r for r in action.rejected}
    assert (refused["system.REQUEST('city')"].action, refused["system.REQUEST('city')"].rule_status) == (
        "SYSTEM.REQUEST", "assumed")
    allowed = {a.call for a in action.allowed or []}
    assert "system.FindRestaurants()" in allowed  # no rule for it: allowed, and the answer must say why
    assert action.call is not None and action.action == _action_of(action.call)
    assert action.rule_status == ("assumed" if action.action == "SYSTEM.REQUEST" else "missing")
    [unlabelled] = engine.next_action(_request(restaurants, {"SYSTEM.REQUEST": rules["SYSTEM.REQUEST"]},
                                               choose_by="line")).actions
    assert {r.rule_status for r in unlabelled.rejected} == {"given"}


def test_later_actions_of_a_turn_are_allowed_in_the_state_they_are_made(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    actions = engine.next_action(_request(restaurants, max_actions=4)).actions
    assert actions and all(a.verified and a.call in {x.call for x in a.allowed or []} for a in actions)


def test_an_empty_history_is_refused_naming_the_history(engine: Engine, restaurants: dict[str, Any]) -> None:
    with pytest.raises(InvalidInput) as err:
        engine.next_action(_request(restaurants, history=""))
    assert err.value.field == "history" and "no object of the acting class (SYSTEM)" in err.value.message


def test_an_empty_event_history_is_the_start_of_a_dialog(engine: Engine, restaurants: dict[str, Any]) -> None:
    [action] = engine.next_action(_request(restaurants, history=[])).actions
    assert action.verified and action.call is not None


def test_a_history_that_violates_the_preconditions_is_answered_and_flagged_with_its_line(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    history = HISTORY + "system.REQUEST('city')\n"
    response = engine.next_action(_request(restaurants, history=history))
    assert response.history_violation is not None
    rules = _request(restaurants).preconditions["SYSTEM.REQUEST"]
    assert response.history_violation.startswith("history, line 5: system.REQUEST('city'): SYSTEM.REQUEST's rule")
    assert response.history_violation.endswith("did not hold"), response.history_violation
    assert any(f"`{rule}`" in response.history_violation for rule in rules), response.history_violation
    assert response.actions[0].verified
    assert engine.next_action(_request(restaurants)).history_violation is None


def test_an_action_not_in_the_spec_is_refused(engine: Engine, restaurants: dict[str, Any]) -> None:
    with pytest.raises(UnknownAction):
        engine.next_action(_request(restaurants, {"SYSTEM.DANCE": ["True"]}))


def test_a_policy_the_engine_is_not_is_refused_not_answered_by_the_base_model(engine: Engine,
                                                                              restaurants: dict[str, Any]) -> None:
    with pytest.raises(InvalidInput) as refused:
        engine.next_action(_request(restaurants, policy="adapter:ad_" + "1" * 24 + "@1"))
    assert refused.value.field == "options.policy"


@pytest.mark.parametrize("options", [{"verify": False}, {"fallback": "greedy"}])
def test_options_of_sampling_are_refused_in_constrained_mode(options: dict[str, Any]) -> None:
    with pytest.raises(ValidationError, match="needs mode 'sample'"):
        NextActionOptions(mode="constrained", **options)
    NextActionOptions(mode="sample", **options)


AGENT_SPEC = """class Env:
  def __init__(self):
    self.seen = set()
  def see(self, *objects): self.seen.update(objects)
class Agent:
  def __init__(self, env):
    self.env = env
  def goto(self, recep): pass
  def take(self, obj, recep): pass
"""


@pytest.mark.parametrize(("choose_by", "max_lines"), [("line", 64), ("line", 2), ("action", 64)])
def test_two_argument_calls_are_chosen_among_the_allowed(engine: Engine, choose_by: str, max_lines: int,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole lines in one pass (`choose_by: line`), or argument by argument: by default (`action`), and for
    `line` beyond MAX_LINES allowed calls."""
    monkeypatch.setattr(constrained, "MAX_LINES", max_lines)
    history = "env = Env()\nagent = Agent(env)\nenv.see('apple 1', 'table 1', 'cup 2')\nagent.goto('table 1')\n"
    rules = {"Agent.goto": ["False"], "Agent.take": ["obj != recep", "obj in self.env.seen"]}
    [action] = engine.next_action(NextActionRequest(
        spec=AGENT_SPEC, preconditions=rules, history=history,
        options={"mode": "constrained", "return_allowed": True, "choose_by": choose_by})).actions
    allowed = {a.call for a in action.allowed or []}
    assert len(allowed) == 6 and "agent.take('apple 1', 'table 1')" in allowed  # 3 x 3 seen, minus obj == recep
    assert action.call in allowed and action.held == rules["Agent.take"]
    scored = [a for a in action.allowed or [] if a.score is not None]
    if choose_by == "line" and max_lines > len(allowed):
        assert len(scored) == 6
    else:  # the last pass scored the second argument only, after the chosen first
        assert scored and len(scored) < 6 and all(a.call.startswith(action.call.rsplit(",", 1)[0]) for a in scored)


def test_choosing_by_line_needs_the_constrained_mode() -> None:
    with pytest.raises(ValidationError, match="choose_by"):
        NextActionOptions(mode="sample", choose_by="line")


def test_a_fine_tuned_policy_asked_without_demonstrations_still_knows_its_domains_arguments(
    tiny: CodeModel, restaurants: dict[str, Any]
) -> None:
    """A BC adapter's calls (`TrainPolicyResult.calls`) give the argument values a demonstration would: without
    them and without demonstrations, no slot name is known and `REQUEST` has nothing to ask for."""
    request = _request(restaurants).model_copy(update={"demonstrations": []})
    with Sandbox(workers=1) as sandbox:
        base = Engine(sandbox, lambda: tiny).next_action(request).actions[0]
        tuned_model = CodeModel(tiny.model, tiny.tokenizer, tiny.info, known_calls=("system.REQUEST('cuisine')",))
        tuned = Engine(sandbox, lambda: tuned_model).next_action(request).actions[0]
    assert "system.REQUEST('cuisine')" not in {a.call for a in base.allowed or []}
    assert "system.REQUEST('cuisine')" in {a.call for a in tuned.allowed or []}


class PrefixScorer:
    """A model whose likelihood of a text is the mass of the lines that start with it, as a real model's is:
    `system.OFFER` also holds every `system.OFFER_INTENT(...)` line."""

    known_calls: tuple[str, ...] = ()

    def __init__(self, tiny: CodeModel, lines: dict[str, float]) -> None:
        self.info, self.lines = tiny.info, lines

    def score(self, prefix: str, continuations: Any, should_stop: Any = None) -> list[float]:
        return [math.log(sum(m for line, m in self.lines.items() if line.startswith(text)) or 1e-12)
                for text in continuations]


def test_an_action_whose_name_starts_another_is_not_credited_with_the_others_mass(
    tiny: CodeModel, restaurants: dict[str, Any]
) -> None:
    """OFFER_INTENT is the likeliest line (0.5 against OFFER's 0.3 in all), but scored as text `system.OFFER`
    holds 0.8: the shorter head must not win on the longer one's mass."""
    lines = {"system.OFFER_INTENT('ReserveRestaurant')\n": 0.5, "system.OFFER('city')\n": 0.15,
             "system.OFFER('cuisine')\n": 0.15, "system.REQUEST('cuisine')\n": 0.2}
    model = PrefixScorer(tiny, lines)
    with Sandbox(workers=1) as sandbox:
        engine = Engine(sandbox, lambda: model)  # type: ignore[arg-type,return-value]
        [action] = engine.next_action(_request(restaurants, preconditions={}, max_actions=1)).actions
    assert action.call == "system.OFFER_INTENT('ReserveRestaurant')"


def test_extensions_are_the_nearest_longer_heads_and_own_mass_subtracts_them() -> None:
    every = ["system.OFFER", "system.OFFER_INTENT", "system.OFFER_INTENT_X", "system.INFORM", "system.REQ_MORE"]
    longer = constrained.extensions(["system.OFFER", "system.INFORM"], every)
    assert longer == {"system.OFFER": ["system.OFFER_INTENT"], "system.INFORM": []}
    scores = {"system.OFFER": math.log(0.8), "system.OFFER_INTENT": math.log(0.5)}
    assert constrained.own_mass("system.OFFER", scores, longer) == pytest.approx(math.log(0.3))
    assert constrained.own_mass("system.OFFER", {**scores, "system.OFFER_INTENT": math.log(0.8)}, longer) \
        == -math.inf
