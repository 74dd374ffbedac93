"""The proxy's MCP server (the SDK's low-level `Server`): the upstreams' tools listed unchanged, and each
`tools/call` recorded, judged (`enforce`, `shadow`) and forwarded to the upstream that has the tool.

Per MCP session (streamable HTTP's `mcp-session-id`; the one connection on stdio) the proxy keeps a recording
(`recorder.Recording`) and a guard session fed the same messages, so a call is judged on exactly the history the
recorded session shows before it. The calls of one session are served one at a time: the record pairs each
result with the call before it, as an agent's log does.

- `record`: forward and record.
- `enforce`: judge first; a refused call never reaches the upstream and comes back as a tool error
  (`isError`) saying which rule did not hold and what would make it hold (`guard.refusal`), recorded as that
  error, as an agent's log records a refused call.
- `shadow`: judge and log the verdict, forward every call.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections import OrderedDict
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import anyio
from mcp import types as mcp_types
from mcp.server import Server, ServerRequestContext
from mcp.shared.exceptions import MCPError

from precond_client.errors import PrecondError
from precond_client.guard import GuardSession, Judge, refusal
from precond_client.mcp.recorder import CallLog, LogFull, Recording, session_name
from precond_client.mcp.upstreams import Upstream, UpstreamFailure, call, routes
from precond_client.schemas import CallVerdict

Mode = Literal["record", "enforce", "shadow"]
MAX_SESSIONS = 256
"""Sessions kept in memory, each with its record's file open (the oldest forgotten first, its file closed; its
record stays on disk, and a call in it later starts a new record)."""
STDIO = "stdio"


@dataclass
class Session:
    recording: Recording
    guard: GuardSession | None
    lock: anyio.Lock = field(default_factory=lambda: anyio.Lock(fast_acquire=True))
    """A session's calls one at a time (taken with no trip through the loop when free)."""
    untold: list[dict[str, Any]] = field(default_factory=list)
    """Messages recorded and not yet given to the guard: given once the call's answer is written (off its path),
    and before the next call is judged at the latest."""

    def catch_up(self) -> None:
        """The guard given the messages recorded so far, so that it judges on the history the record shows."""
        untold, self.untold, guard = self.untold, [], self.guard
        if guard is None:
            return
        for message in untold:
            with suppress(PrecondError):  # the guard session keeps why: its later calls are judged unreadable
                guard.add(message)


class Proxy:
    def __init__(self, upstreams: list[Upstream], mode: Mode, judge: Judge | None, sessions: Path,
                 calls: CallLog, max_log_bytes: int) -> None:
        self.routes = routes(upstreams)
        self.mode = mode
        self.judge = judge
        self.folder = sessions
        self.calls = calls
        self.max_log_bytes = max_log_bytes
        self.sessions: OrderedDict[str, Session] = OrderedDict()
        self.tools = [tool for upstream in upstreams for tool in upstream.tools]
        self.said_full = False

    def server(self) -> Server[Any]:
        server: Server[Any] = Server("precond-mcp", on_list_tools=self.list_tools, on_call_tool=self.call_tool)
        server.middleware = []  # no tracing span per message: the proxy's added latency is its budget
        return server

    async def list_tools(self, ctx: ServerRequestContext[Any], params: mcp_types.PaginatedRequestParams | None
                         ) -> mcp_types.ListToolsResult:
        return mcp_types.ListToolsResult(tools=self.tools)

    def session(self, key: str) -> Session:
        """The session of an MCP session id (`STDIO`: the one connection on stdio), started at its first call."""
        found = self.sessions.get(key)
        if found is None:
            name = session_name() if key == STDIO else f"{session_name()}-{key}"
            guard = self.judge.session() if self.judge is not None and self.mode != "record" else None
            found = self.sessions[key] = Session(Recording.start(self.folder, name, self.max_log_bytes), guard)
            while len(self.sessions) > MAX_SESSIONS:
                self.sessions.popitem(last=False)[1].recording.close()
        return found

    def close(self) -> None:
        """Every record's file closed (each is complete on disk after every call already)."""
        for session in self.sessions.values():
            session.recording.close()

    async def call_tool(self, ctx: ServerRequestContext[Any], params: mcp_types.CallToolRequestParams
                        ) -> mcp_types.CallToolResult:
        headers = getattr(ctx.request, "headers", None)
        key = (headers.get("mcp-session-id") if headers is not None else None) or STDIO
        return await self.call(key, params.name, dict(params.arguments or {}))

    async def call(self, key: str, name: str, arguments: dict[str, Any]) -> mcp_types.CallToolResult:
        """One `tools/call` of the session `key`: its result, or `MCPError` (an unknown tool, a failed upstream)."""
        upstream = self.routes.get(name)
        if upstream is None:
            raise MCPError(mcp_types.INVALID_PARAMS, f"no tool {name[:100]!r} in the upstreams")
        session = self.session(key)
        async with session.lock:
            try:
                self.calls.reserve()
                self.said_full = False
            except LogFull as exc:
                self._full(exc)
                return _error(f"Error: precond mcp did not make the call {name[:100]}: {exc}")
            try:
                return await self._serve(session, upstream, name, arguments)
            finally:
                self.calls.release()

    def _full(self, exc: LogFull) -> None:
        """Said on stderr once per time the bound is reached (the client is told at every call)."""
        if not self.said_full:
            print(f"precond mcp: {exc}", file=sys.stderr, flush=True)
        self.said_full = True

    async def _serve(self, session: Session, upstream: Upstream, name: str, arguments: dict[str, Any]
                     ) -> mcp_types.CallToolResult:
        started = time.perf_counter()
        entry: dict[str, Any] = {"session": session.recording.name, "tool": name, "upstream": upstream.target,
                                 "mode": self.mode}
        try:
            call_id, asked = session.recording.call(name, arguments)
        except LogFull as exc:
            self._log(entry, started, outcome="refused: log full", reason=str(exc))
            return _error(f"Error: precond mcp did not make the call {name}: {exc}")
        entry["call"] = call_id
        verdict = await self._judge(session, name, arguments)
        if verdict is not None:
            entry["verdict"] = _verdict_entry(verdict)
        if verdict is not None and not verdict.allowed and self.mode == "enforce":
            text = refusal(verdict, self.judge.name if self.judge else "")
            self._record(session, asked, call_id, name, text)
            self._log(entry, started, outcome="refused")
            return _error(text)
        forwarded = time.perf_counter()
        try:
            result = await call(upstream, name, arguments)
        except UpstreamFailure as exc:
            self._record(session, asked, call_id, name, f"Error: {exc}")
            self._log(entry, started, outcome="upstream failed", reason=str(exc))
            raise MCPError(mcp_types.INTERNAL_ERROR, str(exc)) from None
        entry["upstream_ms"] = round((time.perf_counter() - forwarded) * 1000, 3)
        self._record(session, asked, call_id, name, result_text(result))
        self._log(entry, started, outcome="error" if result.is_error else "ok")
        return result

    async def _judge(self, session: Session, name: str, arguments: dict[str, Any]) -> CallVerdict | None:
        if session.guard is None:
            return None
        session.catch_up()
        try:
            return await session.guard.acheck(name, arguments)
        except PrecondError as exc:  # the service's guard answers errors as verdicts; anything else fails closed
            return CallVerdict.model_construct(call=name, allowed=False, violations=[], decided={},
                                               error=f"not judged: {exc.message}")

    def _record(self, session: Session, asked: dict[str, Any], call_id: str, name: str, content: str) -> None:
        told = session.recording.result(call_id, name, content)
        if session.guard is not None:
            session.untold += [asked, told]
            asyncio.get_running_loop().call_soon(session.catch_up)  # runs once this task has written the answer

    def _log(self, entry: dict[str, Any], started: float, **said: Any) -> None:
        entry.update(said, ms=round((time.perf_counter() - started) * 1000, 3))
        self.calls.write(entry)


def result_text(result: mcp_types.CallToolResult) -> str:
    """A result as the agent's log would hold it: its text blocks (another block by its type); an error's text
    starts with "Error", which is how the converter and the guard tell a failed call."""
    parts = [b.text if isinstance(b, mcp_types.TextContent) else f"[{b.type}]" for b in result.content]
    text = "".join(parts)
    if not parts and result.structured_content is not None:
        text = json.dumps(result.structured_content)
    if result.is_error and not text.lstrip().lower().startswith("error"):
        text = f"Error: {text}"
    return text


def _error(text: str) -> mcp_types.CallToolResult:
    return mcp_types.CallToolResult(content=[mcp_types.TextContent(text=text)], is_error=True)


def _verdict_entry(verdict: CallVerdict) -> dict[str, Any]:
    return {"allowed": verdict.allowed, "call": verdict.call, "violations": list(verdict.violations),
            "error": verdict.error, "rule_status": verdict.rule_status}

