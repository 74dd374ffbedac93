"""Over HTTP, on a real stack with the gateway's own judgement on: a converter's spec with rules the interpreter
evaluates is answered by the gateway (`judged_by: interpreter`, no job), any other by a worker's sandbox
(`judged_by: sandbox`), with the same verdicts; the latency metric says which; bad input is the same 422."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.stack.local import Stack, check_body, make_stack, serving

EVENTS = [{"actor": "user", "act": "INFORM_INTENT", "args": ["FindRestaurants"]},
          {"actor": "system", "act": "REQUEST", "args": ["city"]},
          {"actor": "system", "act": "REQUEST", "args": ["cuisine"]},
          {"actor": "user", "act": "INFORM", "args": ["city"]},
          {"actor": "user", "act": "INFORM", "args": ["price_range"]}]
"""examples/check-actions.json's history, as events."""
NOT_INTERPRETED = "str(1) == '1'"
"""A rule that always holds and that the interpreter does not evaluate (it calls `str`): the sandbox judges."""


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[httpx.Client]:
    stack: Stack = make_stack(tmp_path_factory.mktemp("interpreted"), tiny_model_dir, PRECOND_INTERPRET_CHECKS="true")
    with serving(stack, workers=1), stack.http() as http:
        yield http


def sandboxed(body: dict[str, Any]) -> dict[str, Any]:
    rules = {**body["preconditions"], "SYSTEM.GOODBYE": [NOT_INTERPRETED]}
    return {**body, "preconditions": rules}


def without_judge(answer: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in answer.items() if k != "judged_by"}


@pytest.mark.parametrize("history", ["program", "events"])
def test_a_converters_spec_is_judged_by_the_gateway_as_the_sandbox_judges_it(client: httpx.Client,
                                                                             history: str) -> None:
    body = check_body("system.FindRestaurants()", "system.INFORM('phone_number')", "system.REQUEST('date')")
    if history == "events":
        body["history"] = EVENTS
    fast = client.post("/check-actions", json=body, params={"wait": 30})
    assert fast.status_code == 200, fast.text
    assert fast.json()["judged_by"] == "interpreter" and "X-Job-Id" not in fast.headers
    slow = client.post("/check-actions", json=sandboxed(body), params={"wait": 30})
    assert slow.status_code == 200, slow.text
    assert slow.json()["judged_by"] == "sandbox" and "X-Job-Id" in slow.headers
    assert without_judge(fast.json()) == without_judge(slow.json())
    assert [v["allowed"] for v in fast.json()["results"]] == [False, False, True]


def test_a_stored_set_is_judged_by_the_gateway(client: httpx.Client) -> None:
    body = check_body()
    made = client.post("/precondition-sets", json={"spec": body["spec"], "preconditions": body["preconditions"]})
    assert made.status_code in (200, 201), made.text
    answer = client.post("/check-actions", json={"precondition_set": made.json()["reference"], "history": EVENTS,
                                                 "calls": body["calls"]})
    assert answer.status_code == 200 and answer.json()["judged_by"] == "interpreter", answer.text
    assert answer.json()["results"][0]["rule_status"] is not None


def test_the_latency_metric_says_what_judged(client: httpx.Client) -> None:
    body = check_body("system.REQUEST('party_size')")
    assert client.post("/check-actions", json=body).status_code == 200
    assert client.post("/check-actions", json=sandboxed(body), params={"wait": 30}).status_code == 200
    metrics = client.get("/metrics").text
    for judge in ("interpreter", "sandbox"):
        assert f'precond_http_request_seconds_count{{judged_by="{judge}",method="POST",route="/check-actions"}}' \
            in metrics, judge


def test_bad_input_is_the_same_422(client: httpx.Client) -> None:
    unknown = client.post("/check-actions", json=check_body("system.REQUESTS('city')"))
    assert unknown.status_code == 422 and unknown.json()["error"]["field"] == "calls[0]", unknown.text
    broken = client.post("/check-actions", json={**check_body(), "preconditions": {"SYSTEM.INFORM": ["assert x"]}})
    assert broken.status_code == 422, broken.text
