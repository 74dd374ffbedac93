"""The MCP servers the proxy fronts, reached with the SDK's own client: a `ClientSession` over `stdio_client` (a
command) or `streamable_http_client` (an `http(s)://` URL). Each tool is routed to the one upstream that lists it;
a name two upstreams list is refused at start, naming both, since a call could not say which one it meant.

A call that fails on the upstream's side (it died, it did not answer within the timeout, it answered something
that is not a `CallToolResult`) raises `UpstreamFailure` naming the upstream: the proxy answers the client with an
MCP error and stays up for the other calls and upstreams. An upstream whose connection closed (its process ended,
its URL stopped answering) is started (or reached) again by the next call to it, within its start timeout; one that
does not come back fails that call, saying why, and the call after it tries again.

A command's `tools/call` requests go on its pipes directly (`link.Link`): the SDK's session still starts it, lists
its tools and answers its own requests, and the result is checked as the session's `send_request` checks it.
"""

from __future__ import annotations

import shlex
from contextlib import AsyncExitStack, suppress
from dataclasses import dataclass, field
from typing import Any

import anyio
from anyio.abc import TaskGroup, TaskStatus
from mcp import ClientSession
from mcp import types as mcp_types
from mcp.client.streamable_http import streamable_http_client
from mcp.shared.exceptions import MCPError
from mcp_types import methods

from precond_client.mcp.link import Link, stdio_link
from precond_client.mcp.sdk_private import clamp_inbound_ttl, later_revision_fields

MAX_TOOL_PAGES = 100
"""`tools/list` pages read from one upstream: a server that keeps answering with a cursor is cut off, said."""


class UpstreamFailure(Exception):
    """An upstream that could not serve a call: the message names it and says what went wrong."""


class StartError(ValueError):
    """The proxy cannot start as asked (an upstream that does not start, a tool name two upstreams list)."""


@dataclass
class Upstream:
    target: str
    """As given to `--upstream`: a command line or a URL; how errors name it."""
    session: ClientSession
    timeout: float
    """Seconds a call may take before the client is told the upstream did not answer."""
    start_timeout: float
    """Seconds it has to start, initialize and list its tools (a Python server's imports take seconds)."""
    tools: list[mcp_types.Tool] = field(default_factory=list)
    gone: str | None = None
    """Why it no longer answers (its connection closed): the next call starts it again first."""
    group: TaskGroup | None = None
    """The task group its connection runs in, where a new one is started (None: it is not started again)."""
    scope: anyio.CancelScope | None = None
    """Its connection's task: cancelled when a new connection replaces it (a process that died leaves its pipes
    and the task that read them, ended here)."""
    reviving: anyio.Lock = field(default_factory=anyio.Lock)
    link: Link | None = None
    """A command's pipes, where its `tools/call` requests are written (None: a URL, reached through the SDK)."""


def is_url(target: str) -> bool:
    return target.startswith(("http://", "https://"))


async def hold(target: str, timeout: float, start_timeout: float, *,
               task_status: TaskStatus[Upstream] = anyio.TASK_STATUS_IGNORED) -> None:
    """One upstream's connection, in a task of its own (`task_group.start(hold, target, ...)` returns the
    `Upstream` once it has listed its tools; `StartError` naming it if it cannot). The SDK's transports run their
    own task groups, which end with an error when the upstream goes (a refused connection, a dead process): that
    error ends this task only, marking the upstream gone, never the proxy."""
    upstream: Upstream | None = None
    started = False
    try:
        async with AsyncExitStack() as stack:
            scope = stack.enter_context(anyio.CancelScope())
            read, write, link = await _transport(stack, target)
            session = await stack.enter_async_context(ClientSession(read, write))
            upstream = Upstream(target, session, timeout, start_timeout, scope=scope, link=link)
            with anyio.fail_after(start_timeout):
                await session.initialize()
                upstream.tools = await _list_tools(session)
            task_status.started(upstream)
            started = True
            await anyio.sleep_forever()
    except StartError:
        raise
    except TimeoutError:
        if not started:
            raise StartError(f"upstream {target!r} did not start: no tools listed within {start_timeout:g} s "
                             "(--start-timeout)") from None
    except Exception as exc:  # any way a process or a URL can fail, or stop, being an MCP server
        if not started or upstream is None:
            raise StartError(f"upstream {target!r} did not start: {_said(exc)}") from None
        if upstream.session is session:  # not yet replaced by a new connection
            upstream.gone = _said(exc)


async def _transport(stack: AsyncExitStack, target: str) -> tuple[Any, Any, Link | None]:
    if is_url(target):
        read, write = await stack.enter_async_context(streamable_http_client(target))
        return read, write, None
    argv = shlex.split(target)
    if not argv:
        raise StartError("--upstream: an empty command")
    return await stack.enter_async_context(stdio_link(argv))


async def _list_tools(session: ClientSession) -> list[mcp_types.Tool]:
    tools: list[mcp_types.Tool] = []
    cursor: str | None = None
    for _ in range(MAX_TOOL_PAGES):
        page = await session.list_tools(params=mcp_types.PaginatedRequestParams(cursor=cursor) if cursor else None)
        tools += page.tools
        cursor = page.next_cursor
        if not cursor:
            return tools
    raise StartError(f"tools/list answered more than {MAX_TOOL_PAGES} pages")


def routes(upstreams: list[Upstream]) -> dict[str, Upstream]:
    """Tool name → its upstream; a name listed by two upstreams is a `StartError` naming both."""
    routed: dict[str, Upstream] = {}
    for upstream in upstreams:
        for tool in upstream.tools:
            other = routed.setdefault(tool.name, upstream)
            if other is not upstream:
                raise StartError(f"tool {tool.name!r} is listed by two upstreams, {other.target!r} and "
                                 f"{upstream.target!r}: a call could not say which one it means")
    return routed


async def call(upstream: Upstream, name: str, arguments: dict[str, Any]) -> mcp_types.CallToolResult:
    """The upstream's result, or `UpstreamFailure` naming it. An MCP error the upstream answers (an unknown tool,
    bad arguments) is its own word and passes as it is, named. The result is parsed as a `CallToolResult` but not
    checked against the tool's output schema, which the client behind the proxy does with the schema it listed
    (it costs about 1 ms a call)."""
    if upstream.gone is not None:
        await revive(upstream)
    try:
        return await _request(upstream, name, arguments)
    except MCPError as exc:
        if exc.code == mcp_types.CONNECTION_CLOSED:
            upstream.gone = _said(exc)
            raise UpstreamFailure(f"upstream {upstream.target!r} is gone: {upstream.gone}") from None
        if exc.code == mcp_types.REQUEST_TIMEOUT:
            raise UpstreamFailure(f"upstream {upstream.target!r} did not answer within {upstream.timeout:g} s "
                                  "(--timeout)") from None
        raise UpstreamFailure(f"upstream {upstream.target!r} answered an error: {_said(exc)}") from None
    except ValueError as exc:  # pydantic's ValidationError among them
        raise UpstreamFailure(f"upstream {upstream.target!r} answered a malformed result: {_said(exc)}") from None
    except Exception as exc:  # a broken pipe or a closed stream: the upstream is gone
        upstream.gone = _said(exc)
        raise UpstreamFailure(f"upstream {upstream.target!r} is gone: {upstream.gone}") from None


async def _request(upstream: Upstream, name: str, arguments: dict[str, Any]) -> mcp_types.CallToolResult:
    """On a command's pipes, checked as the session's `send_request` checks a result (the negotiated version's
    result schema, a later version's fields dropped); on a URL, the session's `send_request` itself."""
    if upstream.link is None:
        request = mcp_types.CallToolRequest(params=mcp_types.CallToolRequestParams(name=name, arguments=arguments))
        return await upstream.session.send_request(request, mcp_types.CallToolResult,
                                                   request_read_timeout_seconds=upstream.timeout)
    raw = await upstream.link.request("tools/call", {"name": name, "arguments": arguments}, upstream.timeout)
    clamp_inbound_ttl(raw)
    version = upstream.session.protocol_version or "2025-11-25"
    with suppress(KeyError):
        methods.validate_server_result("tools/call", version, raw)
    if not (foreign := later_revision_fields("tools/call", version)).isdisjoint(raw):
        raw = {key: value for key, value in raw.items() if key not in foreign}
    return mcp_types.CallToolResult.model_validate(raw, by_name=False)


async def revive(upstream: Upstream) -> None:
    """A new connection for an upstream that is gone (its command started again, its URL reached again), within
    its start timeout; `UpstreamFailure` saying why it is gone and why it did not come back."""
    async with upstream.reviving:
        if upstream.gone is None:  # another call revived it while this one waited
            return
        failed = f"upstream {upstream.target!r} is gone ({upstream.gone})"
        if upstream.group is None:
            raise UpstreamFailure(failed)
        if upstream.scope is not None:
            upstream.scope.cancel()  # the old connection's process and pipes, closed
        try:
            fresh: Upstream = await upstream.group.start(hold, upstream.target, upstream.timeout,
                                                         upstream.start_timeout)
        except StartError as exc:
            raise UpstreamFailure(f"{failed} and did not start again: {_said(exc)}") from None
        upstream.session, upstream.scope, upstream.link = fresh.session, fresh.scope, fresh.link
        upstream.gone = None


def _said(exc: BaseException) -> str:
    """One line of what went wrong: a transport's group of errors said by its first error."""
    while isinstance(exc, BaseExceptionGroup) and exc.exceptions:
        exc = exc.exceptions[0]
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."
