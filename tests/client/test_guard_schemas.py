"""A call whose arguments break its tool's JSON Schema is refused with the schema's reason, by the embedded guard
and by the service's check (the engine, the sandbox) alike, before any rule is asked; the schemas travel in the
spec `precond convert openai` writes. The domain: a shop's support agent, built here in OpenAI's format."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from precond.convert import openai as openai_converter
from precond.convert.shape import ConvertError
from precond.engine.engine import Engine
from precond.sandbox import Sandbox
from precond_client.guard import Guard, refusal
from precond_client.openai_log import converter_spec
from precond_client.schemas import CheckRequest

TOOLS = [
    {"type": "function", "function": {"name": "get_order_details", "description": "Read an order.", "parameters": {
        "type": "object", "properties": {"order_id": {"type": "string"}}, "required": ["order_id"]}}},
    {"type": "function", "function": {"name": "refund_order", "description": "Refund an order.", "parameters": {
        "type": "object", "required": ["order_id", "amount"], "additionalProperties": False,
        "properties": {"order_id": {"type": "string", "pattern": "^(a+)+$"},  # not run: schemas/tool_schemas.py
                       "amount": {"type": "number", "minimum": 0},
                       "reason": {"enum": ["damaged", "late"]}}}}},
]
HISTORY = [
    {"role": "user", "content": "refund order O1"},
    {"role": "assistant", "content": None, "tool_calls": [{"id": "c0", "type": "function", "function": {
        "name": "get_order_details", "arguments": json.dumps({"order_id": "O1"})}}]},
    {"role": "tool", "tool_call_id": "c0", "name": "get_order_details",
     "content": json.dumps({"order_id": "O1", "total": 29.99})},
]
RULES = {"AGENT.refund_order": ["order_id in self.results['get_order_details']"]}
CALLS: list[dict[str, Any]] = [
    {"name": "refund_order", "arguments": {"order_id": "O1", "amount": 29.99}},
    {"name": "refund_order", "arguments": json.dumps({"order_id": "O1", "amount": "29.99"})},
    {"name": "refund_order", "arguments": {"order_id": "O1", "amount": -5}},
    {"name": "refund_order", "arguments": {"order_id": "O1", "amount": 5, "reason": "bored"}},
    {"name": "refund_order", "arguments": {"order_id": "a" * 40 + "!", "amount": 5}},
    {"name": "refund_order", "arguments": {"order_id": "O2", "amount": 5}},
]
EXPECTED = [
    (True, None),
    (False, "arguments break refund_order's JSON Schema: amount: '29.99' is not of type 'number'"),
    (False, "arguments break refund_order's JSON Schema: amount: -5 is less than the minimum of 0"),
    (False, "arguments break refund_order's JSON Schema: reason: 'bored' is not one of ['damaged', 'late']"),
    (False, None),  # its rule refuses it; `pattern` is not run: its regular expression would run outside the sandbox
    (False, None),  # keeps the schema, breaks the rule
]


@pytest.fixture(scope="module")
def spec() -> str:
    return openai_converter.convert([HISTORY], TOOLS, "t.json", "tools.json").spec


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=1) as sandbox:
        yield Engine(sandbox, None)


def test_the_guard_and_the_service_refuse_a_call_that_breaks_its_schema_with_its_reason(spec: str,
                                                                                        engine: Engine) -> None:
    embedded = Guard(spec, RULES).check_actions(HISTORY, CALLS)
    served = engine.check(CheckRequest.model_validate(
        {"spec": spec, "preconditions": RULES, "history": HISTORY, "calls": CALLS}))
    assert [(v.allowed, v.error) for v in embedded.results] == EXPECTED
    assert [v.model_dump() for v in served.results] == [v.model_dump() for v in embedded.results]
    assert served.results[1].call == "agent.refund_order('O1', '29.99', None)"


def test_the_spec_keeps_each_tools_schema_and_is_read_back_as_written(spec: str) -> None:
    tools, _ = converter_spec(spec)
    assert {t.name: t.schema for t in tools} == {t["function"]["name"]: t["function"]["parameters"] for t in TOOLS}


def test_a_tool_whose_parameters_are_no_json_schema_is_refused_naming_it() -> None:
    broken = [{**TOOLS[0], "function": {**TOOLS[0]["function"], "parameters": {
        "type": "object", "properties": {"order_id": {"type": "text"}}}}}]
    with pytest.raises(ConvertError, match=r"tools.json: \[0\].function.parameters: not a JSON Schema: 'text'"):
        openai_converter.convert([HISTORY[:1]], broken, "t.json", "tools.json")


def test_a_schema_the_check_cannot_use_refuses_its_tools_calls(spec: str) -> None:
    unresolvable = spec.replace("'minimum': 0", "'$ref': 'https://example.com/amount.json'")
    verdict = Guard(unresolvable, RULES, fail_closed=False).check(HISTORY, "refund_order",
                                                                  {"order_id": "O1", "amount": 5})
    assert not verdict.allowed and "refund_order's JSON Schema cannot be checked: Unresolvable" in str(verdict.error)


def test_the_models_hint_names_only_what_a_call_can_change(spec: str) -> None:
    """A read the rule waits for can be made; what a rule asks of the records (a delivered order) cannot, and
    the model is told to say so rather than to make the rule hold."""
    rules = {"AGENT.refund_order": ["order_id in self.results['get_order_details']",
                                    "self.results['get_order_details'][order_id]['status'] != 'delivered'"]}
    guard = Guard(spec, rules)
    unread = guard.check(HISTORY[:1], "refund_order", {"order_id": "O1", "amount": 5})
    assert refusal(unread, "g").endswith("Call get_order_details for order_id first, then this call again.")
    delivered = [*HISTORY[:2], {**HISTORY[2], "content": json.dumps({"order_id": "O1", "status": "delivered"})}]
    refused = guard.check(delivered, "refund_order", {"order_id": "O1", "amount": 5})
    assert refused.violations == [rules["AGENT.refund_order"][1]]
    hint = refusal(refused, "g")
    assert hint.endswith("No call of yours can change what its rule asks: tell the user why this cannot be done.")
    assert "Make the rule hold" not in hint and "get_order_details for" not in hint
    broken = guard.check(delivered, "refund_order", {"order_id": "O1", "amount": "5"})
    assert refusal(broken, "g").endswith("Call it again with arguments that keep the tool's schema.")


def test_a_call_sent_as_code_keeps_its_tools_schema_as_its_json_form_does(spec: str, engine: Engine) -> None:
    # `agent.refund_order('O1', '29.99', None)` is the call `{"amount": "29.99"}`: the service refuses it alike
    lines = [v.call for v in engine.check(CheckRequest.model_validate(
        {"spec": spec, "preconditions": RULES, "history": HISTORY, "calls": CALLS})).results]
    as_code = engine.check(CheckRequest.model_validate(
        {"spec": spec, "preconditions": RULES, "history": HISTORY, "calls": lines}))
    assert [(v.allowed, v.error) for v in as_code.results] == EXPECTED
    keywords = engine.check(CheckRequest.model_validate({"spec": spec, "preconditions": RULES, "history": HISTORY,
                                                         "calls": ["agent.refund_order('O1', amount='1')"]}))
    assert keywords.results[0].error == ("arguments break refund_order's JSON Schema: amount: '1' is not of type "
                                         "'number'")
