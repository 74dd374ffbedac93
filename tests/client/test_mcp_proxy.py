"""`precond mcp` as an agent team runs it: the refund desk of examples/mcp (a real MCP server, the SDK's
`MCPServer`) behind the proxy, driven by the SDK's own client over stdio and over streamable HTTP on loopback;
what it records converts and learns with no editing, and what it refuses never reaches the upstream."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from mcp import ClientSession, StdioServerParameters, stdio_client

pytestmark = pytest.mark.stack  # starts the proxy and MCP servers as processes

ROOT = Path(__file__).resolve().parents[2]
DESK = f"{sys.executable} {ROOT / 'examples' / 'mcp' / 'refund_desk.py'}"
REFUND_RULES = {"AGENT.refund_order": ["order_id in self.results['get_order']"], "AGENT.send_note": []}
Calls = Sequence[tuple[str, dict[str, Any]]]


def proxy_args(log: Path, *extra: str, upstreams: Sequence[str] = (DESK,)) -> list[str]:
    return ["-m", "precond.cli", "mcp", *(a for u in upstreams for a in ("--upstream", u)), "--log", str(log),
            *extra]


@asynccontextmanager
async def stdio_proxy(args: list[str]) -> AsyncIterator[ClientSession]:
    params = StdioServerParameters(command=sys.executable, args=args, cwd=str(ROOT))
    async with stdio_client(params) as (read, write), ClientSession(read, write) as session:
        await session.initialize()
        yield session


def texts(result: Any) -> str:
    return "".join(block.text for block in result.content)


def records(log: Path) -> list[dict[str, Any]]:
    return [json.loads(p.read_text()) for p in sorted((log / "sessions").glob("*.json"))]


def call_lines(log: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (log / "calls.jsonl").read_text().splitlines()]


def test_enforce_over_stdio_refuses_a_call_the_rules_forbid_before_the_upstream(tmp_path: Path) -> None:
    rules = tmp_path / "rules.json"
    rules.write_text(json.dumps(REFUND_RULES))
    log = tmp_path / "log"

    async def run() -> tuple[Any, Any, Any, Any]:
        async with stdio_proxy(proxy_args(log, "--mode", "enforce", "--rules", str(rules))) as session:
            listed = await session.list_tools()
            refused = await session.call_tool("refund_order", {"order_id": "A100", "amount": 40})
            read = await session.call_tool("get_order", {"order_id": "A100"})
            allowed = await session.call_tool("refund_order", {"order_id": "A100", "amount": 5})
            return listed, refused, read, allowed

    listed, refused, read, allowed = asyncio.run(run())
    assert [t.name for t in listed.tools] == ["get_order", "refund_order", "send_note"]
    assert refused.is_error
    assert "order_id in self.results['get_order']" in texts(refused)  # the rule, and what would make it hold
    assert "The tool did not run" in texts(refused) and "read what it reads" in texts(refused)
    assert json.loads(texts(read))["refunded"] == 0  # the refused refund never reached the desk
    assert not allowed.is_error and json.loads(texts(allowed))["refunded"] == 5
    [record] = records(log)
    traj = record["traj"]
    assert [m["role"] for m in traj] == ["assistant", "tool"] * 3
    assert traj[1]["content"].startswith("Error: the precondition guard")
    verdicts = [line["verdict"]["allowed"] for line in call_lines(log)]
    assert verdicts == [False, True, True]
    assert [line["outcome"] for line in call_lines(log)] == ["refused", "ok", "ok"]
