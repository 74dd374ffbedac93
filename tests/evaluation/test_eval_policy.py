"""Policy evaluation pieces that need no model: turn segmentation, call spelling, summaries, configs."""

from __future__ import annotations

import pytest

from precond.evaluation.configs import expand, parse_config
from precond.evaluation.domains import Domain
from precond.evaluation.policy import _predict, action_of, parse_policy_config, receivers, segments, summarize_policy
from precond_client.schemas import CheckRequest, CheckResponse, NextActionRequest, NextActionResponse

DIALOG = {
    "program": "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('Find')\nsystem.REQUEST(\"city\")\n"
               "user.INFORM('city')\nsystem.Find()\nsystem.set_query_status(True)\nsystem.OFFER('name')\n",
    "steps": [{"kind": "user_act"}, {"kind": "system_act"}, {"kind": "user_act"}, {"kind": "service_call"},
              {"kind": "query_status"}, {"kind": "system_act"}],
    "turns": [{"speaker": "USER", "steps": [0, 1]}, {"speaker": "SYSTEM", "steps": [1, 2]},
              {"speaker": "USER", "steps": [2, 3]}, {"speaker": "SYSTEM", "steps": [3, 6]}],
}


def test_system_turns_are_split_at_the_query_status() -> None:
    found = list(segments(DIALOG))
    assert [(s.turn, s.reference) for s in found] == [
        (1, ("system.REQUEST('city')",)), (3, ("system.Find()",)), (3, ("system.OFFER('name')",))]
    assert found[2].history.endswith("system.set_query_status(True)\n")
    assert found[1].history.endswith("user.INFORM('city')\n")


def test_summary_merges_segments_into_turns() -> None:
    results = [
        {"dialog": "d", "turn": 3, "predicted": ["system.Find()"], "reference": ["system.Find()"],
         "compatible": [True], "seconds": 1.0},
        {"dialog": "d", "turn": 3, "predicted": ["system.OFFER('x')"], "reference": ["system.OFFER('name')"],
         "compatible": [False], "seconds": 3.0},
    ]
    summary = summarize_policy(results)
    assert summary["turns"] == 1
    assert summary["f1"] == pytest.approx(0.5)
    assert summary["compatibility"] == 0.5
    assert summary["latency_p95_s"] == 3.0


def test_policy_config_names() -> None:
    config = parse_policy_config("gt/both/shots=3")
    assert (config.source, config.in_prompt, config.verify, config.shots) == ("gt", True, True, 3)
    with pytest.raises(ValueError):
        parse_policy_config("none/verify/shots=1")
    bc = parse_policy_config("inferred/constrained/shots=0/bc")
    assert (bc.policy, bc.mode, bc.shots) == ("bc", "constrained", 0)
    assert parse_policy_config("none/plain/shots=1").policy == "act"
    assert parse_policy_config("inferred/verify/shots=1/react").policy == "react"
    with pytest.raises(ValueError):
        parse_policy_config("none/plain/shots=1/thoughts")


def test_inference_config_names() -> None:
    config = parse_config("model+enumerate/recency/spp=4/demos=2")
    options = config.infer_options()
    assert (options.generators, options.ranking, options.samples_per_prompt, config.demos) == (
        ["model", "enumerate"], "recency", 4, 2)
    assert parse_config("always").baseline == "always"
    assert [c.name for c in expand("baselines,gt")] == ["always", "gt"]
    with pytest.raises(ValueError):
        parse_config("model/greedy")


def test_only_calls_of_domain_actions_count_as_actions() -> None:
    known = receivers("user = USER()\nsystem = SYSTEM(user)\n")
    assert action_of("system.INFORM('city')", known) == "SYSTEM.INFORM"
    assert action_of("user.NEGATE_INTENT()", known) == "USER.NEGATE_INTENT"
    assert action_of("hello there", known) is None


def test_probe_config_reranks_its_base_inference() -> None:
    config = parse_config("enumerate/recency/maxrate=0.9/demos=4")
    assert config.max_rate == 0.9
    assert config.base.name == "enumerate/recency/demos=4"
    assert config.base.max_rate is None


class _RecordingEngine:
    """Answers every next-action request with nothing, and keeps the requests to look at."""

    def __init__(self) -> None:
        self.requests: list[NextActionRequest] = []

    def next_action(self, request: NextActionRequest) -> NextActionResponse:
        self.requests.append(request)
        return NextActionResponse(actions=[])

    def check(self, request: CheckRequest) -> CheckResponse:
        raise AssertionError("not used")


def test_react_rows_ask_for_thoughts_on_dialogs_whose_demonstrations_carry_none() -> None:
    domain = Domain("d", "sgd", "class SYSTEM:\n    def GOODBYE(self):\n        pass\n", ("system.GOODBYE()\n",),
                    ("SYSTEM.GOODBYE",), (), (), {}, {})
    segment = next(iter(segments(DIALOG)))
    asked = {}
    for name in ("none/plain/shots=1", "inferred/constrained/shots=1/react"):
        engine = _RecordingEngine()
        _predict(engine, domain, parse_policy_config(name), {}, segment, seed=0)
        asked[name] = engine.requests[0].options.think
    assert asked == {"none/plain/shots=1": False, "inferred/constrained/shots=1/react": True}
