"""An assumed rule of a tool call is about the call (precond/engine/judging/call_facts.py): "the call right before
succeeded" held at every demonstrated refund, yet a refund after a failed look-up of another parcel is allowed."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.call_facts import about_the_call
from precond.engine.judging.ranking import Candidate, Cluster
from precond.engine.judging.report import Ranked
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {"parcel_id": {"type": "string"}}, "required": ["parcel_id"]}}}
    for name in ("get_parcel", "refund_parcel")]
REFUND = "AGENT.refund_parcel"


def call(tool: str, pid: str, result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": tool,
                                                               "arguments": json.dumps({"parcel_id": pid})}}]},
            {"role": "tool", "content": result if isinstance(result, str) else json.dumps(result)}]


def run(pid: str, failed_first: str | None = None) -> list[dict[str, object]]:
    """A refund after the parcel was read and the user confirmed; optionally a failed read of another parcel
    between (a typo the user corrected)."""
    steps: list[dict[str, object]] = [
        {"role": "user", "content": f"refund {pid}"}, *call("get_parcel", pid, {"parcel_id": pid, "state": "lost"}),
        {"role": "assistant", "content": "Refund it?"}, {"role": "user", "content": "yes"}]
    if failed_first:
        steps += call("get_parcel", failed_first, "Error: parcel not found")
    return [*steps, *call("refund_parcel", pid, {"ok": True})]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, None)


def test_a_refund_right_after_a_failed_call_is_not_refused_by_the_last_call_succeeding(engine: Engine) -> None:
    demos = convert([run(p) for p in ("A1", "B2", "C3", "D4", "E5")], TOOLS)
    response = engine.infer(InferRequest.model_validate({
        "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories], "actions": [REFUND],
        "options": {"generators": ["enumerate"]}}))
    rules = response.preconditions[REFUND]
    assert "self.last_ok" not in rules
    assert any("parcel_id in self.results['get_parcel']" in r for r in rules), rules
    lines = convert([run("F6", failed_first="F7")], TOOLS).trajectories[0].program.splitlines()
    at = max(k for k, line in enumerate(lines) if ".refund_parcel(" in line)
    verdict = engine.check(CheckRequest(spec=demos.spec, preconditions=response.preconditions,
                                        history="\n".join(lines[:at]) + "\n", calls=[lines[at]])).results[0]
    assert verdict.allowed, verdict


def test_only_assumed_rules_about_no_part_of_the_call_are_dropped() -> None:
    read, flown = "parcel_id in self.results['get_parcel']", "parcel_id in self.results['get_parcel'] and x"
    texts = (read, "self.last_ok", "self.user.messages", flown, "self.results")
    chosen = [Cluster((Candidate(e, "enumerate", 0b1),)) for e in texts]
    ranked = Ranked(results=[], valid=[], clusters=chosen, chosen=chosen, decided={
        read: "established", "self.last_ok": "assumed", "self.user.messages": "assumed", flown: "assumed",
        "self.results": "established"})
    out = about_the_call(ranked, ("self", "parcel_id"))
    assert [c.representative.expression for c in out.chosen] == [read, "self.user.messages", flown, "self.results"]
    assert out.reasons["self.last_ok"].startswith("dropped: assumed")
