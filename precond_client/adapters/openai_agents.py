"""The OpenAI Agents SDK: a tool input guardrail that judges each function-tool call against a precondition set,
given the run's items so far, and when it refuses tells the model why instead of running the tool.

    agent = protect(agent, Guard.from_set(client.get_set("ps_...@3")))

`protect` returns a copy of the agent whose function tools carry the guardrail and whose hooks follow the run:
before each model call (`on_llm_start`) the items the model is given, which hold every earlier call and result,
are added to the run's guard session (only the new ones: `Conversation`), and after it (`on_llm_end`) the calls
the model asked for are tied to that session, so that the guardrail judges each call on the history before it.
Hosted tools are not function tools and are not guarded; a handoff's agent is guarded when it is protected too.
The items are the client-side history the SDK keeps; a run whose history lives on the server
(`previous_response_id`, `conversation_id`) gives the model only the new items and is not supported.
"""

from __future__ import annotations

import copy
import weakref
from collections.abc import Collection, Sequence
from typing import Any

from agents import Agent, AgentHooks, FunctionTool, RunContextWrapper
from agents.items import ModelResponse, TResponseInputItem
from agents.lifecycle import AgentHooksBase
from agents.models.chatcmpl_converter import Converter
from agents.tool_guardrails import ToolGuardrailFunctionOutput, ToolInputGuardrail, ToolInputGuardrailData

from precond_client.adapters.conversation import Conversation, unjudged
from precond_client.guard import Judge, refusal

NOT_FOLLOWED = ("the guard has not seen this run's items: the agent's hooks did not run (give the agent to "
                "`protect`, not the guardrail alone)")


def chat_messages(items: Sequence[TResponseInputItem]) -> list[dict[str, Any]]:
    """The SDK's own conversion of Responses items to chat messages, each tool result named after its call.
    The new items of a step are mostly function calls and their string outputs: those are converted here as the
    SDK converts them (`calls_and_outputs`), at a fraction of the converter's cost per item."""
    quick = calls_and_outputs(items)
    if quick is not None:
        return quick
    names = {_field(i, "call_id"): _field(i, "name") for i in items if _field(i, "type") == "function_call"}
    messages = [dict(m) for m in Converter.items_to_messages(list(items))]
    for message in messages:
        if message.get("role") == "tool" and message.get("tool_call_id") in names:
            message["name"] = names[message["tool_call_id"]]
    return messages


def calls_and_outputs(items: Sequence[Any]) -> list[dict[str, Any]] | None:
    """`chat_messages` of items that are all function calls (dicts, string arguments) and their string outputs,
    as `Converter.items_to_messages` gives them: consecutive calls in one assistant message, each output a tool
    message named after its call; None for any other item, left to the converter."""
    messages: list[dict[str, Any]] = []
    calls: list[dict[str, Any]] | None = None
    names: dict[str, str] = {}
    for item in items:
        kind = item.get("type") if type(item) is dict else None
        if kind == "function_call" and _plain_call(item):
            if calls is None:
                calls = []
                messages.append({"role": "assistant", "content": None, "tool_calls": calls})
            names[item["call_id"]] = item["name"]
            calls.append({"id": item["call_id"], "type": "function",
                          "function": {"name": item["name"], "arguments": item["arguments"] or "{}"}})
        elif kind == "function_call_output" and type(item.get("output")) is str and type(item.get("call_id")) is str:
            calls = None
            messages.append({"role": "tool", "tool_call_id": item["call_id"], "content": item["output"]})
        else:
            return None
    for message in messages:
        if message["role"] == "tool" and message["tool_call_id"] in names:
            message["name"] = names[message["tool_call_id"]]
    return messages


def _plain_call(item: dict[str, Any]) -> bool:
    return (type(item.get("call_id")) is str and type(item.get("name")) is str
            and type(item.get("arguments")) is str and "provider_data" not in item)


def _field(item: Any, name: str) -> Any:
    return item.get(name) if isinstance(item, dict) else getattr(item, name, None)


class ToolGuard:
    """One guard for any number of runs and agents: each run (its context) has its own conversation."""

    def __init__(self, judge: Judge) -> None:
        self.judge = judge
        self.runs: weakref.WeakKeyDictionary[RunContextWrapper[Any], Conversation] = weakref.WeakKeyDictionary()
        self.calls: dict[str, tuple[Conversation, RunContextWrapper[Any]]] = {}
        """call id → the run that the model asked it in (tied in `on_llm_end`, taken by the guardrail)."""
        self.guardrail: ToolInputGuardrail[Any] = ToolInputGuardrail(self.judge_call, name="precondition_guard")

    def protect(self, agent: Agent[Any], tools: Collection[str] | None = None) -> Agent[Any]:
        """A copy of `agent` with the guardrail on its function tools (or on those named in `tools`)."""
        guarded = []
        for tool in agent.tools:
            if isinstance(tool, FunctionTool) and (tools is None or tool.name in tools):
                tool = copy.copy(tool)
                tool.tool_input_guardrails = [*(tool.tool_input_guardrails or []), self.guardrail]
            guarded.append(tool)
        return agent.clone(tools=guarded, hooks=GuardHooks(self, agent.hooks))

    def follow(self, context: RunContextWrapper[Any], items: Sequence[TResponseInputItem]) -> None:
        conversation = self.runs.get(context)
        if conversation is None:
            conversation = self.runs[context] = Conversation(self.judge, chat_messages)
        conversation.follow(items)

    def asked(self, context: RunContextWrapper[Any], response: ModelResponse) -> None:
        conversation = self.runs.get(context)
        for gone in [i for i, (_, run) in self.calls.items() if run is context]:
            del self.calls[gone]  # calls of the run's earlier responses that no guardrail took (unguarded tools)
        if conversation is not None:
            for item in response.output:
                if _field(item, "type") == "function_call":
                    self.calls[str(_field(item, "call_id"))] = (conversation, context)

    async def judge_call(self, data: ToolInputGuardrailData) -> ToolGuardrailFunctionOutput:
        context = data.context
        found = self.calls.pop(context.tool_call_id, None)
        if found is None:
            verdict = unjudged(self.judge, context.tool_name, NOT_FOLLOWED)
        else:
            verdict = await found[0].session.acheck(context.tool_name, context.tool_arguments)
        if verdict.allowed:
            return ToolGuardrailFunctionOutput.allow(output_info=verdict)
        return ToolGuardrailFunctionOutput.reject_content(refusal(verdict, self.judge.name), output_info=verdict)


class GuardHooks(AgentHooks[Any]):
    """The agent's hooks, with the run's items followed before each model call; every event also goes to the
    hooks the agent had (`inner`)."""

    def __init__(self, guard: ToolGuard, inner: AgentHooksBase[Any, Any] | None) -> None:
        self.guard = guard
        self.inner = inner

    async def on_llm_start(self, context: RunContextWrapper[Any], agent: Agent[Any], system_prompt: str | None,
                           input_items: list[TResponseInputItem]) -> None:
        self.guard.follow(context, input_items)
        if self.inner is not None:
            await self.inner.on_llm_start(context, agent, system_prompt, input_items)

    async def on_llm_end(self, context: RunContextWrapper[Any], agent: Agent[Any], response: ModelResponse) -> None:
        self.guard.asked(context, response)
        if self.inner is not None:
            await self.inner.on_llm_end(context, agent, response)

    async def on_start(self, context: Any, agent: Any) -> None:
        if self.inner is not None:
            await self.inner.on_start(context, agent)

    async def on_end(self, context: Any, agent: Any, output: Any) -> None:
        if self.inner is not None:
            await self.inner.on_end(context, agent, output)

    async def on_handoff(self, context: Any, agent: Any, source: Any) -> None:
        if self.inner is not None:
            await self.inner.on_handoff(context, agent, source)

    async def on_tool_start(self, context: Any, agent: Any, tool: Any) -> None:
        if self.inner is not None:
            await self.inner.on_tool_start(context, agent, tool)

    async def on_tool_end(self, context: Any, agent: Any, tool: Any, result: Any) -> None:
        if self.inner is not None:
            await self.inner.on_tool_end(context, agent, tool, result)


def protect(agent: Agent[Any], judge: Judge, tools: Collection[str] | None = None) -> Agent[Any]:
    """`agent`, its function tool calls judged by `judge` (a `Guard` or a `ServiceGuard`)."""
    return ToolGuard(judge).protect(agent, tools)
