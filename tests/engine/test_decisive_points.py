"""A tool-calling agent's conditions are judged where they decide something (precond/engine/judging/decisive.py): at the
calls, at the earlier steps of the same run with the call's arguments, and at a bounded sample of the rest, so
that many runs leave the work budget to the search instead of to pairing every step with every call's arguments."""

from __future__ import annotations

import json

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.decisive import MAX_SAMPLE, decisive_points
from precond.sandbox import Sandbox
from precond.sandbox.types import ActionInfo, Limits, Point, Position, TraceResult
from precond_client.schemas import InferOptions, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
    for name, params in [("get_order_details", ("order_id",)), ("cancel_pending_order", ("order_id", "reason"))]]


def trace_of(runs: int, steps: int) -> tuple[TraceResult, ActionInfo]:
    """`runs` runs of `steps` steps, the agent made at step 0 (`AGENT.result` there) and one call at the end."""
    calls = tuple(Point(d, steps - 1, (f"#W{d}",)) for d in range(runs))
    info = ActionInfo("AGENT.cancel", ("order_id",), True, calls, tuple(c.args for c in calls))
    made = ActionInfo("AGENT.result", ("tool",), False, tuple(Point(d, 1, ("x",)) for d in range(runs)), (("x",),))
    positions = tuple(tuple(Position(k + 1, "x") for k in range(steps)) for _ in range(runs))
    return TraceResult({"AGENT.cancel": info, "AGENT.result": made}, positions), info


def test_the_calls_and_their_earlier_steps_are_kept_and_the_rest_is_sampled() -> None:
    trace, info = trace_of(runs=200, steps=20)  # 4,000 steps x 200 argument tuples = 800,000 points
    points = decisive_points(trace, info, ["AGENT.cancel", "AGENT.result"])
    assert points is not None
    decisive = {Point(d, p, (f"#W{d}",)) for d in range(200) for p in range(1, 20)}  # since the agent exists
    assert decisive <= set(points) and set(info.occurrences) <= set(points)
    assert len(points) == len(decisive) + MAX_SAMPLE and len(set(points)) == len(points)
    assert not any(p.position == 0 for p in points)  # before the agent exists there is nothing to judge
    assert points == decisive_points(trace, info, ["AGENT.cancel", "AGENT.result"])  # the same request, the same


def test_a_small_grid_keeps_its_default_points() -> None:
    trace, info = trace_of(runs=5, steps=6)
    assert decisive_points(trace, info, ["AGENT.cancel", "AGENT.result"]) is None


def call(tool: str, arguments: dict[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": tool, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def order_run(n: int, status: str) -> list[dict[str, object]]:
    steps: list[dict[str, object]] = [{"role": "user", "content": "please cancel"}]
    for other in range(6):  # reads of other orders: steps that pair with every call's arguments
        steps += call("get_order_details", {"order_id": f"#X{n}-{other}"}, {"status": "delivered"})
    steps += call("get_order_details", {"order_id": f"#W{n}"}, {"order_id": f"#W{n}", "status": status})
    return steps + call("cancel_pending_order", {"order_id": f"#W{n}", "reason": "no longer needed"}, {})


def test_many_runs_leave_the_work_budget_to_the_search() -> None:
    """120 runs of 16 steps: 1,900+ steps x 120 calls' arguments are 230,000 points a condition; a budget of
    2,000,000 judged every condition at all of them stopped the enumerator after 8. At the decisive points the
    whole grammar is judged within it, and the order's status is among what it found."""
    converted = convert([order_run(n, "pending") for n in range(120)], TOOLS)
    request = InferRequest(spec=converted.spec, demonstrations=[t.program for t in converted.trajectories],
                           actions=["AGENT.cancel_pending_order"],
                           options=InferOptions(generators=["enumerate"], candidates="all"))
    with Sandbox(Limits(max_points=2_000_000), workers=1) as sandbox:
        response = Engine(sandbox, None).infer(request)
    assert "the enumerator stopped" not in response.warnings.get("AGENT.cancel_pending_order", "")
    judged = {c.assertion for c in response.candidates["AGENT.cancel_pending_order"]}
    read = "order_id in self.results['get_order_details']"
    assert f"{read} and self.results['get_order_details'][order_id]['status'] == 'pending'" in judged
    assert read in response.preconditions["AGENT.cancel_pending_order"]


def test_a_candidate_that_runs_out_of_time_is_dropped_and_counted_and_the_request_answers() -> None:
    converted = convert([order_run(n, "pending") for n in range(3)], TOOLS)
    request = InferRequest(spec=converted.spec, demonstrations=[t.program for t in converted.trajectories],
                           actions=["AGENT.cancel_pending_order"], options=InferOptions(
                               generators=["enumerate"], candidates="all",
                               prior_rules={"AGENT.cancel_pending_order": ["order_id != 10 ** 10 ** 8"]}))
    with Sandbox(Limits(timeout_s=3, cpu_s=30, unit_cpu_s=30), workers=1) as sandbox:
        response = Engine(sandbox, None).infer(request)
    assert "order_id in self.results['get_order_details']" in response.preconditions["AGENT.cancel_pending_order"]
    assert "1 candidate(s) dropped: they ran out of time" in response.warnings["AGENT.cancel_pending_order"]
