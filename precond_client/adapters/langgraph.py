"""LangGraph and LangChain: each tool call of a `ToolNode` judged against a precondition set before the tool
runs; a refused call answers the model with a `ToolMessage` (status "error") that says why.

    tool_node = guarded_tool_node(tools, Guard.from_set(client.get_set("ps_...@3")))  # in place of ToolNode(tools)

The judging is the ToolNode's tool-call wrapper (`wrap_tool_call` / `awrap_tool_call`), the interception point
LangGraph provides; LangChain's `create_agent` takes the same judging as a middleware
(`precond_client.adapters.langchain_agents.GuardMiddleware`).
The history is the graph state's messages, converted by LangChain's `convert_to_openai_messages` and added to the
thread's guard session as they grow (`Conversation`); a thread is the `thread_id` of the run's config.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

from langchain_core.messages import AIMessage, BaseMessage, HumanMessage, ToolMessage
from langchain_core.messages.utils import convert_to_openai_messages
from langchain_core.tools import BaseTool
from langgraph.prebuilt import ToolNode
from langgraph.prebuilt.tool_node import ToolCallRequest
from langgraph.types import Command

from precond_client.adapters.conversation import Conversation
from precond_client.guard import Judge, refusal
from precond_client.schemas import CallVerdict

MAX_THREADS = 1024
"""Threads whose sessions are kept (the least recently judged go first, and are read again from their
messages if they come back)."""
Result = ToolMessage | Command[Any]


def chat_messages(messages: Sequence[BaseMessage]) -> list[dict[str, Any]]:
    """LangChain's `convert_to_openai_messages`, message by message (it reads each message alone); the common
    ones (`plain_message`) converted here as it converts them, at a fraction of its cost."""
    converted: list[dict[str, Any]] = []
    for message in messages:
        plain = plain_message(message)
        converted.extend([plain] if plain is not None else convert_to_openai_messages([message]))
    return converted


PLAIN_ROLES: dict[type, str] = {AIMessage: "assistant", HumanMessage: "user", ToolMessage: "tool"}


def plain_message(message: Any) -> dict[str, Any] | None:
    """A human, AI or tool message (those very classes) whose content is a string, as `convert_to_openai_messages`
    gives it; None for any other message."""
    role = PLAIN_ROLES.get(type(message))
    if role is None or type(message.content) is not str:
        return None
    converted: dict[str, Any] = {"role": role}
    if message.name:
        converted["name"] = message.name
    if role == "assistant" and message.tool_calls:
        converted["tool_calls"] = [{"type": "function", "id": call["id"], "function": {
            "name": call["name"], "arguments": json.dumps(call["args"], ensure_ascii=False)}}
            for call in message.tool_calls]
    if message.additional_kwargs.get("refusal"):
        converted["refusal"] = message.additional_kwargs["refusal"]
    if role == "tool":
        converted["tool_call_id"] = message.tool_call_id
    converted["content"] = message.content
    return converted


class GuardedToolCalls:
    """The wrapper of a `ToolNode`'s tool calls: `ToolNode(tools, wrap_tool_call=g.wrap, awrap_tool_call=g.awrap)`."""

    def __init__(self, judge: Judge, messages_key: str = "messages") -> None:
        self.judge = judge
        self.messages_key = messages_key
        self.threads: OrderedDict[str, Conversation] = OrderedDict()
        self.lock = threading.Lock()

    def wrap(self, request: ToolCallRequest, execute: Callable[[ToolCallRequest], Result]) -> Result:
        call = request.tool_call
        verdict = self._conversation(request).session.check(call["name"], call.get("args") or {})
        return execute(request) if verdict.allowed else self._refused(request, verdict)

    async def awrap(self, request: ToolCallRequest,
                    execute: Callable[[ToolCallRequest], Awaitable[Result]]) -> Result:
        call = request.tool_call
        verdict = await self._conversation(request).session.acheck(call["name"], call.get("args") or {})
        return await execute(request) if verdict.allowed else self._refused(request, verdict)

    def _conversation(self, request: ToolCallRequest) -> Conversation:
        config = getattr(request.runtime, "config", None) or {}
        thread = str((config.get("configurable") or {}).get("thread_id", ""))
        with self.lock:
            conversation = self.threads.pop(thread, None) or Conversation(self.judge, chat_messages)
            self.threads[thread] = conversation
            while len(self.threads) > MAX_THREADS:
                self.threads.popitem(last=False)
        conversation.follow(self._messages(request.state))
        return conversation

    def _messages(self, state: Any) -> Sequence[BaseMessage]:
        found = state if isinstance(state, list) else (state.get(self.messages_key) if isinstance(state, dict)
                                                       else getattr(state, self.messages_key, None))
        return found if isinstance(found, list) else list(found or [])

    def _refused(self, request: ToolCallRequest, verdict: CallVerdict) -> ToolMessage:
        call = request.tool_call
        return ToolMessage(content=refusal(verdict, self.judge.name), tool_call_id=call["id"] or "",
                           name=call["name"], status="error")


def guarded_tool_node(tools: Sequence[BaseTool | Callable[..., Any]], judge: Judge, **options: Any) -> ToolNode:
    """A `ToolNode` of `tools` whose calls `judge` (a `Guard` or a `ServiceGuard`) decides first; `options` are
    the ToolNode's own (`messages_key`, `handle_tool_errors`, ...)."""
    calls = GuardedToolCalls(judge, options.get("messages_key", "messages"))
    return ToolNode(tools, wrap_tool_call=calls.wrap, awrap_tool_call=calls.awrap, **options)
