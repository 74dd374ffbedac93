"""`/check-actions` for a tool-calling LLM agent, on a real stack (Redis, gateway, a worker with the real
sandbox): the history as the agent's OpenAI chat messages, the calls as `{"name", "arguments"}`, rules over
the spec `precond convert openai` writes; bad messages are a 422 naming the message, never a 500."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.convert.openai import convert
from precond_client import Client, ToolCall

TAU = Path(__file__).resolve().parents[1] / "fixtures" / "tau_airline"
RECORDS = json.loads((TAU / "trajectories.json").read_text())
SPEC = convert(RECORDS, json.loads((TAU / "tools.json").read_text())).spec
READ = "reservation_id in self.results['get_reservation_details']"
RULES = {"AGENT.cancel_reservation": [READ, f"{READ} and self.results['get_reservation_details'][reservation_id]"
                                              "['cabin'] == 'business'"]}
CANCEL = {"name": "cancel_reservation", "arguments": '{"reservation_id": "FDZ0T5"}'}


def history_until_the_cancellation() -> list[dict[str, Any]]:
    """Task 30's successful run up to its first cancellation (of FDZ0T5, a business reservation it read)."""
    traj = RECORDS[1]["traj"]
    at = next(i for i, m in enumerate(traj) for c in m.get("tool_calls") or []
              if c["function"]["name"] == "cancel_reservation")
    return traj[:at]


def check(client: httpx.Client, history: list[dict[str, Any]], calls: list[Any]) -> httpx.Response:
    body = {"spec": SPEC, "preconditions": RULES, "history": history, "calls": calls}
    return client.post("/check-actions", json=body, params={"wait": 30})


def test_a_tool_call_is_judged_on_the_agents_messages(client: httpx.Client) -> None:
    history = history_until_the_cancellation()
    answer = check(client, history, [CANCEL, {"name": "cancel_reservation", "arguments": {"reservation_id": "ZZZ999"}}])
    assert answer.status_code == 200, answer.text
    allowed, unread = answer.json()["results"]
    assert allowed == {"call": "agent.cancel_reservation('FDZ0T5')", "action": "AGENT.cancel_reservation",
                       "rule_status": "given", "allowed": True, "violations": [], "decided": {}, "error": None}
    assert unread["allowed"] is False and READ in unread["violations"]  # the rule names what refuses it
    # the user's words and the tools' results are data: a quote in them cannot become code
    hostile = [*history, {"role": "user", "content": "x'); import os; os._exit(1); ('"}]
    assert check(client, hostile, [CANCEL]).json()["results"][0]["allowed"] is True


def test_the_python_client_speaks_it(stack: Any) -> None:
    with Client(stack.base_url) as client:
        call = ToolCall(name="cancel_reservation", arguments={"reservation_id": "X1"})
        verdict = client.check_actions({"spec": SPEC, "preconditions": RULES,
                                        "history": history_until_the_cancellation(), "calls": [call]})
    assert verdict.results[0].call == "agent.cancel_reservation('X1')" and not verdict.results[0].allowed


@pytest.mark.parametrize(("change", "field", "words"), [
    (lambda h: h.append("hello"), "history[{n}]", "valid dictionary"),
    (lambda h: h.append({"role": "tool", "content": "{}"}), "history[{n}]", "pairs with no call"),
    (lambda h: h.append({"role": "assistant", "tool_calls": [{"function": {"name": "drop_db", "arguments": "{}"}}]}),
     "history[{n}].tool_calls[0].function.name", "no tool 'drop_db'"),
    (lambda h: h.append({"role": "assistant", "tool_calls": [
        {"function": {"name": "cancel_reservation", "arguments": "{reservation_id: 1"}}]}),
     "history[{n}].tool_calls[0].function.arguments", "not valid JSON"),
])
def test_bad_messages_are_a_422_naming_the_message(client: httpx.Client, change: Any, field: str,
                                                    words: str) -> None:
    history = history_until_the_cancellation()
    change(history)
    answer = check(client, history, [CANCEL])
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == field.format(n=len(history) - 1) and words in error["message"], error


def test_a_bad_tool_call_is_a_422_naming_the_call(client: httpx.Client) -> None:
    answer = check(client, history_until_the_cancellation(), [CANCEL, {"name": "cancel_reservation",
                                                                       "arguments": {"booking": "X"}}])
    assert answer.status_code == 422 and answer.json()["error"]["field"] == "calls[1].arguments", answer.text
    assert "has no parameter 'booking'" in answer.json()["error"]["message"]
