"""The adapters' own conversions of a framework's items to chat messages give what the frameworks' converters give,
and a conversation followed step by step through an adapter is judged as the embedded guard judges the whole
history: drawn histories of reads, cancellations and their results, split into steps at random."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from langchain_core.messages import AIMessage, BaseMessage, HumanMessage, SystemMessage, ToolMessage
from langchain_core.messages.utils import convert_to_openai_messages

from precond.evaluation import tools
from precond_client.adapters import langgraph
from precond_client.adapters.conversation import Conversation
from precond_client.errors import PrecondError
from precond_client.guard import Guard

TAU = Path(__file__).resolve().parents[1] / "fixtures" / "tau_airline"
READ = "reservation_id in self.results['get_reservation_details']"
GUARD = Guard(tools.load(TAU).spec, {"AGENT.cancel_reservation": [READ]})
NAMES = st.sampled_from(["get_reservation_details", "cancel_reservation"])
IDS = st.sampled_from(["c1", "c2", "c3"])
TEXT = st.text(max_size=12)
ARGUMENTS = st.one_of(st.sampled_from(["", "{}"]),
                      st.builds(lambda r: json.dumps({"reservation_id": r}), st.sampled_from(["R1", "R2"])))
RESULT = st.sampled_from([json.dumps({"reservation_id": r, "user_id": "u1", "cabin": "business"})
                          for r in ("R1", "R2")] + ["Error: not found", ""])


def sdk_reference(items: list[Any]) -> list[dict[str, Any]]:
    """The SDK's converter over the whole list, each tool result named after its call (the SDK is imported by
    the tests that use it: collecting this module, in every test process, stays cheap)."""
    from agents.models.chatcmpl_converter import Converter

    names = {i["call_id"]: i["name"] for i in items if isinstance(i, dict) and i.get("type") == "function_call"}
    messages = [dict(m) for m in Converter.items_to_messages(list(items))]
    for message in messages:
        if message.get("role") == "tool" and message.get("tool_call_id") in names:
            message["name"] = names[message["tool_call_id"]]
    return messages


SDK_CALL = st.builds(lambda i, n, a: {"type": "function_call", "call_id": i, "name": n, "arguments": a},
                     IDS, NAMES, ARGUMENTS)
SDK_OUTPUT = st.builds(lambda i, o: {"type": "function_call_output", "call_id": i, "output": o}, IDS, RESULT)
SDK_OTHER = st.one_of(
    st.builds(lambda t: {"role": "user", "content": t}, TEXT),
    st.builds(lambda i, t: {"type": "function_call_output", "call_id": i,
                            "output": [{"type": "input_text", "text": t}]}, IDS, TEXT),
    st.builds(lambda c: c | {"provider_data": {"model": "m"}}, SDK_CALL))
SDK_ITEMS = st.lists(st.one_of(SDK_CALL, SDK_OUTPUT, SDK_CALL, SDK_OUTPUT, SDK_OTHER), max_size=8)


def test_the_agents_sdk_items_convert_as_the_sdk_converts_them(examples: Callable[[int], int]) -> None:
    from precond_client.adapters import openai_agents

    @given(SDK_ITEMS)
    @settings(max_examples=examples(300), deadline=None)
    def converted_as_the_sdk_converts(items: list[Any]) -> None:
        assert openai_agents.chat_messages(items) == sdk_reference(items)

    converted_as_the_sdk_converts()


TOOL_CALL = st.builds(lambda i, n, r: {"name": n, "args": {"reservation_id": r}, "id": i, "type": "tool_call"},
                      IDS, NAMES, st.sampled_from(["R1", "é"]))
LANGCHAIN_MESSAGES = st.lists(st.one_of(
    st.builds(HumanMessage, TEXT),
    st.builds(lambda t, c, n: AIMessage(t, tool_calls=c, name=n), TEXT, st.lists(TOOL_CALL, max_size=2),
              st.none() | st.just("agent")),
    st.builds(lambda c: AIMessage([{"type": "text", "text": "a"}], tool_calls=c), st.lists(TOOL_CALL, max_size=1)),
    st.builds(lambda t, r: AIMessage(t, additional_kwargs={"refusal": r}), TEXT, TEXT),
    st.builds(lambda o, i, n, s: ToolMessage(o, tool_call_id=i, name=n, status=s), RESULT, IDS,
              st.none() | NAMES, st.sampled_from(["success", "error"])),
    st.builds(lambda t: ToolMessage([{"type": "text", "text": t}], tool_call_id="c1"), TEXT),
    st.builds(SystemMessage, TEXT)), max_size=8)


def test_langchain_messages_convert_as_langchain_converts_them(examples: Callable[[int], int]) -> None:
    @given(LANGCHAIN_MESSAGES)
    @settings(max_examples=examples(300), deadline=None)
    def converted_as_langchain_converts(messages: list[BaseMessage]) -> None:
        assert langgraph.chat_messages(messages) == list(convert_to_openai_messages(messages))

    converted_as_langchain_converts()


def steps(history: list[Any], cuts: list[int]) -> list[list[Any]]:
    """The growing list a framework hands over at each step: the history up to each cut, then all of it."""
    return [history[:cut] for cut in sorted(set(cuts)) if cut <= len(history)] + [history]


def verdict_after(history: list[Any], cuts: list[int], to_messages: Any) -> dict[str, Any]:
    conversation = Conversation(GUARD, to_messages)
    for step in steps(history, cuts):
        session = conversation.follow(step)
    return session.check("cancel_reservation", {"reservation_id": "R1"}).model_dump()


def whole(messages: list[dict[str, Any]]) -> dict[str, Any]:
    try:
        session = GUARD.session(messages)
    except PrecondError:  # a history the guard cannot read: the adapter judges its calls unreadable
        return {"unreadable": True}
    return session.check("cancel_reservation", {"reservation_id": "R1"}).model_dump()


def same(adapter: dict[str, Any], embedded: dict[str, Any]) -> None:
    if embedded == {"unreadable": True}:
        assert adapter["allowed"] is False and adapter["error"].startswith("not judged")
    else:
        assert adapter == embedded


def sdk_turn(n: int, name: str, arguments: str, output: str) -> list[dict[str, Any]]:
    """A call and its output, the call's id its own (as the SDK's are)."""
    return [{"type": "function_call", "call_id": f"call_{n}", "name": name, "arguments": arguments},
            {"type": "function_call_output", "call_id": f"call_{n}", "output": output}]


def test_the_agents_sdk_adapter_judges_as_the_embedded_guard(examples: Callable[[int], int]) -> None:
    from precond_client.adapters import openai_agents

    @given(st.lists(st.tuples(NAMES, ARGUMENTS, RESULT), max_size=5), st.lists(st.integers(0, 12), max_size=4))
    @settings(max_examples=examples(150), deadline=None)
    def judged_as_the_embedded_guard(turns: list[tuple[str, str, str]], cuts: list[int]) -> None:
        history: list[Any] = [{"role": "user", "content": "cancel R1"},
                              *(i for n, turn in enumerate(turns) for i in sdk_turn(n, *turn))]
        same(verdict_after(history, cuts, openai_agents.chat_messages), whole(sdk_reference(history)))

    judged_as_the_embedded_guard()


def langchain_turn(n: int, name: str, reservation: str, output: str) -> list[BaseMessage]:
    return [AIMessage("", tool_calls=[{"name": name, "args": {"reservation_id": reservation}, "id": f"call_{n}"}]),
            ToolMessage(output, tool_call_id=f"call_{n}", name=name)]


def test_the_langgraph_adapter_judges_as_the_embedded_guard(examples: Callable[[int], int]) -> None:
    @given(st.lists(st.tuples(NAMES, st.sampled_from(["R1", "R2"]), RESULT), max_size=5),
           st.lists(st.integers(0, 12), max_size=4))
    @settings(max_examples=examples(150), deadline=None)
    def judged_as_the_embedded_guard(turns: list[tuple[str, str, str]], cuts: list[int]) -> None:
        history: list[Any] = [HumanMessage("cancel R1"),
                              *(m for n, turn in enumerate(turns) for m in langchain_turn(n, *turn))]
        same(verdict_after(history, cuts, langgraph.chat_messages),
             whole(list(convert_to_openai_messages(history))))

    judged_as_the_embedded_guard()
