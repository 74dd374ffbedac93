"""LangChain's `create_agent`: each tool call judged against a precondition set before the tool runs, as an agent
middleware; a refused call answers the model with a `ToolMessage` (status "error") that says why.

    agent = create_agent(model, tools, middleware=[GuardMiddleware(Guard.from_set(client.get_set("ps_...@3")))])

The judging is the LangGraph adapter's (`GuardedToolCalls`), so an agent built either way is guarded alike: the
history is the agent state's messages, a thread is the `thread_id` of the run's config. Both hooks are given, so
the agent runs guarded with `invoke` and with `ainvoke`.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

from langchain.agents.middleware import AgentMiddleware
from langgraph.prebuilt.tool_node import ToolCallRequest

from precond_client.adapters.langgraph import GuardedToolCalls, Result
from precond_client.guard import Judge


class GuardMiddleware(AgentMiddleware[Any, Any, Any]):
    """`create_agent(..., middleware=[GuardMiddleware(judge)])`: `judge` (a `Guard` or a `ServiceGuard`)
    decides each tool call first."""

    def __init__(self, judge: Judge, messages_key: str = "messages") -> None:
        super().__init__()
        self.calls = GuardedToolCalls(judge, messages_key)

    def wrap_tool_call(self, request: ToolCallRequest, handler: Callable[[ToolCallRequest], Result]) -> Result:
        return self.calls.wrap(request, handler)

    async def awrap_tool_call(self, request: ToolCallRequest,
                              handler: Callable[[ToolCallRequest], Awaitable[Result]]) -> Result:
        return await self.calls.awrap(request, handler)
