"""Labelled calls through the service: `/infer-preconditions` with `counterexamples` answers rules that refuse
the calls labelled 'refuse' and name them; a label that names no call, or one call labelled both ways, is a 422
naming the field (the worker's check, as the CLI's exit 2)."""

from __future__ import annotations

from typing import Any

import httpx

from tests.engine.test_counterexamples import CALL_LINE, CANCEL, DEMOS, LABELS, OTHERS, request, run


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


def _ok(answer: httpx.Response, status: int = 200) -> dict[str, Any]:
    assert answer.status_code == status, answer.text
    return answer.json()  # type: ignore[no-any-return]


def test_a_reviewed_call_is_kept_with_the_set_and_its_next_version_refuses_it_naming_it(
    client: httpx.Client
) -> None:
    """`POST /precondition-sets/{id}/counterexamples`: a judged call that should have been refused is re-inferred
    with; the next version refuses it, its rule's evidence names it, and later versions keep it."""
    demos = [t.program for i, t in enumerate(DEMOS.trajectories) if i != 2]  # no basic-economy call demonstrated
    enumerate_only = {"generators": ["enumerate"]}
    inferred = _ok(client.post("/infer-preconditions", params={"wait": 120}, json={
        "spec": DEMOS.spec, "demonstrations": demos, "actions": [CANCEL], "options": enumerate_only}))
    made = _ok(client.post("/precondition-sets", json={
        "spec": DEMOS.spec, "preconditions": inferred["preconditions"], "demonstrations": demos,
        "evidence": inferred["evidence"], "candidates": inferred["candidates"]}), 201)
    history, call = run("F6", "economy", "no")[:3], {"name": "cancel_reservation",
                                                     "arguments": '{"reservation_id": "F6"}'}

    def judged(reference: str) -> dict[str, Any]:
        return _ok(client.post("/check-actions", params={"wait": 60}, json={
            "precondition_set": reference, "history": history, "calls": [call]}))["results"][0]  # type: ignore[no-any-return]

    assert judged(made["reference"])["allowed"]  # economy without insurance: the rules learned from logs allow it
    new = _ok(client.post(f"/precondition-sets/{made['id']}/counterexamples", params={"wait": 120}, json={
        "history": history, "call": call, "verdict": "refuse", "base_version": 1, "options": enumerate_only}))
    assert new["version"] == 2 and len(new["counterexamples"]) == 1
    name = new["counterexamples"][0]["calls"][0]["name"]
    assert name == "review 1: agent.cancel_reservation('F6')"
    assert new["counterexamples"][0]["calls"][0]["verdict"] == "refuse"
    refusing = [rule for rule, e in new["evidence"][CANCEL].items() if name in e["refuses"]]
    assert refusing and set(refusing) <= set(new["preconditions"][CANCEL]), new["evidence"][CANCEL]
    verdict = judged(new["reference"])
    assert not verdict["allowed"] and set(refusing) & set(verdict["violations"]), verdict
    assert new["validation"]["blocked"] == []  # the demonstrated cancellations stay allowed
    edited = _ok(client.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "require", "action": CANCEL, "rule": refusing[0]}]}), 201)
    assert edited["counterexamples"] == new["counterexamples"]  # an edit keeps them for the next re-inference

    for bad, field in (({"call": "agent.says('hi')"}, "call"),  # not an action: 422 naming the call
                       ({"call": "agent.fly_away()"}, "call"),
                       ({"history": [{"role": "robot"}]}, "history[0]")):
        answer = client.post(f"/precondition-sets/{made['id']}/counterexamples",
                             json={"history": history, "call": call, "verdict": "refuse"} | bad)
        assert answer.status_code == 422, answer.text
        assert answer.json()["error"]["field"].startswith(field), answer.text
    for verdict, said in (("refuse", "already labelled"), ("allow", "the other way ('refuse')")):
        answer = client.post(f"/precondition-sets/{made['id']}/counterexamples",
                             json={"history": history, "call": call, "verdict": verdict})
        assert answer.status_code == 422 and answer.json()["error"]["field"] == "call", answer.text
        assert said in answer.json()["error"]["message"] and name in answer.json()["error"]["message"]
    assert _ok(client.get(f"/precondition-sets/{made['id']}"))["latest"] == 3  # nothing stored by a refusal
