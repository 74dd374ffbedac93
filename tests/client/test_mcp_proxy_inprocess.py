"""The MCP proxy's own work, in this process with a stand-in upstream (no transport, no child process): the
verdicts `enforce` and `shadow` log are the embedded guard's on the recorded history, for any sequence of calls
(hypothesis); `calls.jsonl` is bounded and a call past its bound is refused, named; the stdio wire's reads and
writes."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import anyio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcp import types as mcp_types

from precond_client.guard import Guard
from precond_client.mcp import fastpath, pipes
from precond_client.mcp.proxy import Mode, Proxy
from precond_client.mcp.recorder import CallLog, prepare
from precond_client.mcp.tools import function_schema, spec_for
from precond_client.mcp.upstreams import Upstream

ORDER = {"type": "object", "properties": {"order_id": {"type": "string"}, "amount": {"type": "integer"}},
         "required": ["order_id"]}
TOOLS = [mcp_types.Tool(name=name, description=name, input_schema=ORDER)
         for name in ("get_order", "refund_order", "send_note")]
RULES = {"AGENT.refund_order": ["order_id in self.results['get_order']"],
         "AGENT.send_note": ["order_id in self.results['get_order']", "self.last_ok"]}


class Desk:
    """An upstream's session that answers every call at once: an order read, or an error for an unknown one."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    async def send_request(self, request: Any, result_type: Any, request_read_timeout_seconds: float | None = None
                           ) -> mcp_types.CallToolResult:
        params = request.params
        self.calls.append(params.name)
        order = str(params.arguments.get("order_id"))
        if order.startswith("X"):
            return mcp_types.CallToolResult(content=[mcp_types.TextContent(text=f"no order {order}")], is_error=True)
        return mcp_types.CallToolResult(content=[mcp_types.TextContent(text=json.dumps({"order_id": order}))])


def proxy_of(folder: Path, mode: Mode, *, calls_bytes: int = 1 << 30) -> tuple[Proxy, Upstream, Guard]:
    upstream = Upstream("desk", Desk(), 5.0, 5.0, list(TOOLS))  # type: ignore[arg-type]
    guard = Guard(spec_for([function_schema(tool) for tool in TOOLS]), RULES)
    proxy = Proxy([upstream], mode, guard, prepare(folder), CallLog(folder, calls_bytes), 1 << 30)
    return proxy, upstream, guard


class Context:
    """What the proxy reads of a request's context: its HTTP headers (none: one stdio session)."""

    request = None


async def call(proxy: Proxy, name: str, arguments: dict[str, Any]) -> mcp_types.CallToolResult:
    params = mcp_types.CallToolRequestParams(name=name, arguments=arguments)
    return await proxy.call_tool(Context(), params)  # type: ignore[arg-type]


def lines(folder: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (folder / "calls.jsonl").read_text().splitlines()]


CALL = st.tuples(st.sampled_from(["get_order", "refund_order", "send_note"]),
                 st.fixed_dictionaries({"order_id": st.sampled_from(["A1", "A2", "X9"])},
                                       optional={"amount": st.integers(0, 5)}))


@pytest.mark.parametrize("mode", ["enforce", "shadow"])
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(calls=st.lists(CALL, min_size=1, max_size=8))
def test_each_verdict_is_the_embedded_guards_on_the_recorded_history(
        tmp_path_factory: pytest.TempPathFactory, mode: Mode, calls: list[tuple[str, dict[str, Any]]]) -> None:
    folder = tmp_path_factory.mktemp("log")
    proxy, upstream, guard = proxy_of(folder, mode)

    async def run() -> list[mcp_types.CallToolResult]:
        return [await call(proxy, name, arguments) for name, arguments in calls]

    results = anyio.run(run)
    proxy.calls.close()
    [record] = [json.loads(path.read_text()) for path in (folder / "sessions").glob("*.json")]
    logged = lines(folder)
    reached = [name for (name, _), line in zip(calls, logged, strict=True) if line["outcome"] != "refused"]
    assert upstream.session.calls == reached  # type: ignore[attr-defined]
    for n, ((name, arguments), line, result) in enumerate(zip(calls, logged, results, strict=True)):
        expected = guard.session(record["traj"][: 2 * n]).check(name, arguments)
        assert line["verdict"]["allowed"] == expected.allowed, n
        assert line["verdict"]["violations"] == expected.violations
        assert line["verdict"]["call"] == expected.call
        assert (line["outcome"] == "refused") == (mode == "enforce" and not expected.allowed)
        assert result.is_error == (line["outcome"] != "ok")


def test_calls_jsonl_is_bounded_and_a_call_past_its_bound_is_refused_named(tmp_path: Path) -> None:
    proxy, upstream, _ = proxy_of(tmp_path, "shadow", calls_bytes=96 * 1024)

    async def run() -> list[mcp_types.CallToolResult]:
        return [await call(proxy, "get_order", {"order_id": f"A{n}"}) for n in range(400)]

    results = anyio.run(run)
    proxy.calls.close()
    refused = [r for r in results if r.is_error]
    assert refused and not any(r.is_error for r in results[:100])
    text = refused[0].content[0].text  # type: ignore[union-attr]
    assert "calls.jsonl" in text and "--max-calls-bytes" in text and str(96 * 1024) in text
    assert (tmp_path / "calls.jsonl").stat().st_size <= 96 * 1024
    assert len(lines(tmp_path)) + len(refused) == 400  # every call made is logged; the others were refused
    assert len(upstream.session.calls) == len(lines(tmp_path))  # type: ignore[attr-defined]
    [record] = [json.loads(path.read_text()) for path in (tmp_path / "sessions").glob("*.json")]
    assert len(record["traj"]) == 2 * len(lines(tmp_path))  # a refused call is not in the training record


def test_calls_jsonl_moved_away_at_its_bound_is_started_again(tmp_path: Path) -> None:
    """A log rotated by moving the full file away (as logrotate does) makes room again: no restart needed."""
    proxy, _, _ = proxy_of(tmp_path, "shadow", calls_bytes=64 * 1024)

    async def run(count: int) -> list[mcp_types.CallToolResult]:
        return [await call(proxy, "get_order", {"order_id": "A1"}) for _ in range(count)]

    assert anyio.run(run, 400)[-1].is_error
    (tmp_path / "calls.jsonl").rename(tmp_path / "calls.1.jsonl")
    assert not anyio.run(run, 1)[0].is_error
    proxy.calls.close()
    assert len(lines(tmp_path)) == 1


async def unused(name: str, arguments: dict[str, Any]) -> mcp_types.CallToolResult:
    raise AssertionError("called")


def test_the_stdio_wire_is_read_in_lines_and_written_whole_on_the_loop(monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """The proxy's own pipe reads and writes: lines as the SDK reads them (bad UTF-8 replaced, a last line without
    its newline), a write larger than the pipe holds finished whole while the other end reads, and a message past
    the bound cut off, said."""
    inbound, feed = os.pipe()
    os.set_blocking(inbound, False)
    os.write(feed, b'{"a": 1}\n{"b": "\xff"}\npartial')
    os.close(feed)

    async def read_all(fd: int) -> list[str]:
        lines = fastpath.Lines(pipes.PipeWriter(-1), unused)
        async with pipes.reading(fd, pipes.LineReader(lines.feed, lines.end, "the wire")):
            return [line async for line in lines]

    assert anyio.run(read_all, inbound) == ['{"a": 1}\n', '{"b": "\ufffd"}\n', "partial"]
    os.close(inbound)

    outbound, sink = os.pipe()
    os.set_blocking(sink, False)
    big = "x" * (4 << 20) + "\n"

    async def write_and_read() -> str:
        lines = fastpath.Lines(pipes.PipeWriter(-1), unused)
        reader = pipes.LineReader(lines.feed, lines.end, "the wire")
        async with anyio.create_task_group() as group, pipes.reading(outbound, reader):
            group.start_soon(pipes.PipeWriter(sink).write, big)
            return await anext(lines)

    os.set_blocking(outbound, False)
    assert anyio.run(write_and_read) == big
    os.close(sink)
    os.close(outbound)

    monkeypatch.setattr(pipes, "MAX_LINE", 1024)
    endless, feed = os.pipe()
    os.set_blocking(endless, False)
    os.write(feed, b"y" * 4096)
    assert anyio.run(read_all, endless) == []
    assert "more than 1024 bytes without a newline" in capsys.readouterr().err
    os.close(feed)
    os.close(endless)
