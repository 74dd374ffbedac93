"""`precond mcp`: the upstreams started (or reached), their tools checked and written to `tools.json`, the
judge made for those tools, and the proxy served on stdio or on streamable HTTP on 127.0.0.1 (the SDK's
transports), until its client goes (stdio) or it is stopped (HTTP)."""

from __future__ import annotations

import gc
import json
import os
from collections.abc import Callable, Sequence
from contextlib import AsyncExitStack
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import anyio

from precond_client.guard import Judge
from precond_client.mcp.proxy import STDIO, Mode, Proxy
from precond_client.mcp.recorder import CallLog, prepare
from precond_client.mcp.stdio import serving_stdio
from precond_client.mcp.tools import function_schema
from precond_client.mcp.upstreams import StartError, hold

MakeJudge = Callable[[Sequence[dict[str, Any]]], Judge | None]
"""The upstreams' tools (OpenAI function schemas) → the judge of their calls (None in `record`)."""


@dataclass(frozen=True)
class Settings:
    upstreams: Sequence[str]
    mode: Mode
    log: Path
    http: int | None = None
    timeout: float = 30.0
    """Seconds an upstream has to answer a call before the client is told it did not."""
    max_log_bytes: int = 8 * 1024 * 1024
    """Bound of one session's record."""
    max_calls_bytes: int = 256 * 1024 * 1024
    """Bound of `calls.jsonl`."""
    start_timeout: float = 120.0
    """Seconds an upstream has to start and list its tools (at start, and again after its connection closed)."""


async def serve(settings: Settings, make_judge: MakeJudge) -> None:
    """Serve until the client (stdio) or a signal (HTTP) ends it; `StartError` when it cannot start."""
    sessions = prepare(settings.log)
    async with AsyncExitStack() as stack:
        held = await stack.enter_async_context(anyio.create_task_group())
        stack.callback(held.cancel_scope.cancel)  # the upstreams' connections end with the proxy
        upstreams = [await held.start(hold, target, settings.timeout, settings.start_timeout)
                     for target in settings.upstreams]
        for upstream in upstreams:
            upstream.group = held  # where a connection that closed is opened again
        schemas = [function_schema(tool) for upstream in upstreams for tool in upstream.tools]
        judge = make_judge(schemas)
        calls = CallLog(settings.log, settings.max_calls_bytes)
        stack.callback(calls.close)
        proxy = Proxy(upstreams, settings.mode, judge, sessions, calls, settings.max_log_bytes)
        stack.callback(proxy.close)
        _write_private(settings.log / "tools.json", json.dumps(schemas, indent=2) + "\n")
        server = proxy.server()
        _settle()
        if settings.http is None:
            async with serving_stdio(partial(proxy.call, STDIO)) as (read, write):
                await server.run(read, write, server.create_initialization_options())
            return
        import uvicorn

        app = server.streamable_http_app(host="127.0.0.1")
        config = uvicorn.Config(app, host="127.0.0.1", port=settings.http, log_level="warning", lifespan="on")
        await uvicorn.Server(config).serve()


def _settle() -> None:
    """The objects made at start (the SDK's and pydantic's schemas, the judge: some 100,000) kept out of the
    collector's later passes: a full pass over them takes ~100 ms, which the call that triggers it waits."""
    gc.collect()
    gc.freeze()


def _write_private(path: Path, text: str) -> None:
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
        handle.write(text)


__all__ = ["MakeJudge", "Settings", "StartError", "serve"]
