"""Labelled calls through the service: `/infer-preconditions` with `counterexamples` answers rules that refuse
the calls labelled 'refuse' and name them; a label that names no call, or one call labelled both ways, is a 422
naming the field (the worker's check, as the CLI's exit 2)."""

from __future__ import annotations

from typing import Any

import httpx

from tests.engine.test_counterexamples import CALL_LINE, CANCEL, LABELS, OTHERS, request


def body(counterexamples: list[dict[str, Any]]) -> dict[str, Any]:
    return request(counterexamples).model_dump(mode="json", exclude_defaults=True) | {
        "counterexamples": counterexamples}


def test_labelled_calls_are_learned_from_and_bad_ones_are_422_naming_the_field(client: httpx.Client) -> None:
    answer = client.post("/infer-preconditions", json=body(LABELS), params={"wait": 120})
    assert answer.status_code == 200, answer.text
    evidence = answer.json()["evidence"][CANCEL]
    assert {n for e in evidence.values() for n in e["refuses"]} == {
        "C3 basic economy", "E5 basic economy", "F6 economy uninsured"}

    no_call = [{"demonstration": 0, "calls": [{"line": 3, "verdict": "refuse"}]}]
    answer = client.post("/infer-preconditions", json=body(no_call), params={"wait": 120})
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"]["field"] == "counterexamples[0].calls[0].line"

    same = OTHERS.trajectories[0].program
    both = [{"program": same, "calls": [{"line": CALL_LINE, "verdict": "refuse"}]},
            {"program": same, "calls": [{"line": CALL_LINE, "verdict": "allow"}]}]
    answer = client.post("/infer-preconditions", json=body(both), params={"wait": 120})
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == "counterexamples[1].calls[0]" and "counterexamples[0].calls[0]" in error["message"]
