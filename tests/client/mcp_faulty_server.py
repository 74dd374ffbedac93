"""An MCP server (the SDK's low-level `Server`, on stdio) that fails the ways an upstream can: `hang` never
answers, `die` ends the process mid-call, `malformed` answers a result that is not a `CallToolResult`, `echo`
works. The proxy's tests put it behind `precond mcp`; its tool names are its argument's prefix
(`python mcp_faulty_server.py x_` lists `x_echo`, ...), so two of them can be fronted at once."""

from __future__ import annotations

import json
import os
import sys
from typing import Any

import anyio
from mcp import types
from mcp.server import Server, ServerRequestContext
from mcp.server.stdio import stdio_server

PREFIX = sys.argv[1] if len(sys.argv) > 1 else ""
WIRE = os.dup(1)
"""The protocol's stdout, kept before the SDK's transport points fd 1 away from it (stray prints go to stderr)."""
SCHEMA = {"type": "object", "properties": {"text": {"type": "string"}}}


async def list_tools(ctx: ServerRequestContext[Any], params: Any) -> types.ListToolsResult:
    return types.ListToolsResult(tools=[types.Tool(name=f"{PREFIX}{n}", description=n, input_schema=SCHEMA)
                                        for n in ("echo", "hang", "die", "malformed")])


async def call_tool(ctx: ServerRequestContext[Any], params: types.CallToolRequestParams) -> Any:
    name = params.name.removeprefix(PREFIX)
    if name == "hang":
        await anyio.sleep_forever()
    if name == "die":
        os._exit(3)
    if name == "malformed":  # the SDK's server checks its results: this answer is written past it
        raw = {"jsonrpc": "2.0", "id": ctx.request_id, "result": {"content": "not a list of blocks"}}
        os.write(WIRE, (json.dumps(raw) + "\n").encode())
        await anyio.sleep_forever()
    text = str((params.arguments or {}).get("text", ""))
    return types.CallToolResult(content=[types.TextContent(text=text)])


async def main() -> None:
    server: Server[Any] = Server("faulty", on_list_tools=list_tools, on_call_tool=call_tool)
    async with stdio_server() as (read, write):
        await server.run(read, write, server.create_initialization_options())


if __name__ == "__main__":
    anyio.run(main)
