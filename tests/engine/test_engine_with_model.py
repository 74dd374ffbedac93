"""The engine end to end with the real embedded code model (Qwen2.5-Coder-0.5B, CPU): slow, so kept small."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.models import ModelSettings, load_code_model
from precond.sandbox import Sandbox
from precond_client.schemas import InferRequest, NextActionRequest

pytestmark = pytest.mark.model




@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    model = load_code_model(ModelSettings(path="embedded", threads=1))
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, lambda: model)


def test_model_candidates_are_validated_and_ranked(engine: Engine, restaurants: dict[str, Any]) -> None:
    response = engine.infer(InferRequest(
        spec=restaurants["spec_program"],
        demonstrations=[d["program"] for d in restaurants["demos"]],
        actions=["SYSTEM.INFORM", "SYSTEM.GOODBYE", "SYSTEM.NOTIFY_SUCCESS"],
        options={"generators": ["model"], "prompts_per_action": 1, "samples_per_prompt": 8, "seed": 0,
                 "candidates": "all", "library": False},  # the model's candidates alone (no library priors)
    ))
    assert response.model is not None and response.model.name
    for action in ("SYSTEM.INFORM", "SYSTEM.GOODBYE", "SYSTEM.NOTIFY_SUCCESS"):
        counts = response.stats.actions[action]
        assert counts.sampled == 8 and counts.parsed >= 1, (action, counts)
        assert all(c.source == "model" for c in response.candidates[action])
    # invalid candidates say where they failed; the model finds NOTIFY_SUCCESS's condition and it is valid
    invalid = [c for cands in response.candidates.values() for c in cands if not c.valid]
    assert invalid and all(c.reason and ("demonstration" in c.reason or "not separated from chance" in c.reason)
                           for c in invalid)
    notify = [c.assertion for c in response.candidates["SYSTEM.NOTIFY_SUCCESS"] if c.valid]
    assert any("query_success" in a for a in notify), response.candidates["SYSTEM.NOTIFY_SUCCESS"]
    assert response.stats.seconds["generate"] > 0
    engine._sandbox.trace(response.program, [d["program"] for d in restaurants["demos"]])


def test_next_action_is_a_verified_system_act(engine: Engine, restaurants: dict[str, Any]) -> None:
    gt = {f"SYSTEM.{a}": list(v) for a, v in restaurants["gt_preconditions"].items()}
    history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\n"
    response = engine.next_action(NextActionRequest(
        spec=restaurants["spec_program"], preconditions=gt,
        demonstrations=[d["program"] for d in restaurants["demos"][:2]], history=history,
        options={"mode": "sample", "max_attempts": 4, "max_actions": 1, "seed": 0},
    ))
    [action] = response.actions
    assert action.call.startswith("system.") and 1 <= action.attempts <= 4
    assert action.verified, action


def test_constrained_next_action_requests_a_slot_the_user_has_not_given(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    gt = {f"SYSTEM.{a}": list(v) for a, v in restaurants["gt_preconditions"].items()}
    history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\nuser.INFORM('city')\n"
    response = engine.next_action(NextActionRequest(
        spec=restaurants["spec_program"], preconditions=gt,
        demonstrations=[d["program"] for d in restaurants["demos"][:1]], history=history,
        options={"mode": "constrained", "max_actions": 1, "return_allowed": True},
    ))
    [action] = response.actions
    assert action.verified and action.call in {a.call for a in action.allowed or []}
    assert action.call.startswith("system.REQUEST(") and action.call != "system.REQUEST('city')", action
