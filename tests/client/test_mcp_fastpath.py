"""The proxy's own `tools/call` paths beside the MCP SDK's: an upstream's answer read off its pipe (`link`) is the
result, or the failure, that the SDK's client session makes of the same answer (hypothesis); calls from several
sessions on one upstream each get their own answer; and on the client's wire, a plain call is answered beside the
SDK's server while anything else reaches the SDK as it came."""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Awaitable, Callable
from typing import Any

import anyio
import mcp_types as types
import pytest
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream
from hypothesis import given, settings
from hypothesis import strategies as st
from mcp import ClientSession

from precond_client.mcp import fastpath, pipes
from precond_client.mcp.link import Link, _parsed
from precond_client.mcp.upstreams import Upstream, UpstreamFailure, call

Answer = Callable[[dict[str, Any]], Awaitable[dict[str, Any] | None]]
"""A stand-in upstream: a request → the JSON-RPC answer it writes (None: none)."""


class Stdin:
    """The upstream's stdin as `Link` writes it, here a memory stream of bytes."""

    def __init__(self, stream: MemoryObjectSendStream[bytes]) -> None:
        self.stream = stream

    async def write(self, text: str) -> None:
        await self.stream.send(text.encode())


async def pump(link: Link, stdout: MemoryObjectReceiveStream[bytes]) -> None:
    """The upstream's stdout as the loop reads it: each chunk to the link's line reader as it comes, then its
    end."""
    reader = pipes.LineReader(link.received, link.ended, "up")
    async with stdout:
        async for chunk in stdout:
            reader.data_received(chunk)
    reader.eof_received()
    reader.connection_lost(None)


async def serve_pipe(requests: MemoryObjectReceiveStream[bytes], answers: MemoryObjectSendStream[bytes],
                     answer: Answer) -> None:
    """The upstream's side of its pipes: each request line answered with a line (in a task of its own)."""
    async def reply(request: dict[str, Any]) -> None:
        said = await answer(request)
        if said is not None:
            await answers.send((json.dumps(said) + "\n").encode())

    async with answers, anyio.create_task_group() as group:
        async for line in requests:
            group.start_soon(reply, json.loads(line))


async def serve_session(requests: MemoryObjectReceiveStream[Any], answers: MemoryObjectSendStream[Any],
                        answer: Answer) -> None:
    """The same upstream behind the SDK's session: its messages as `stdio_client` writes and reads them."""
    async with answers:
        async for message in requests:
            said = await answer(json.loads(message.message.model_dump_json(by_alias=True, exclude_unset=True)))
            if said is not None:
                await answers.send(_parsed(json.dumps(said).encode()))


async def through_link(answer: Answer, name: str = "tool") -> types.CallToolResult | str:
    to_upstream, requests = anyio.create_memory_object_stream[bytes](16)
    answers, from_upstream = anyio.create_memory_object_stream[bytes](16)
    link = Link(Stdin(to_upstream))  # type: ignore[arg-type]
    upstream = Upstream("up", Unnegotiated(), 5.0, 5.0, link=link)  # type: ignore[arg-type]
    said: types.CallToolResult | str = "no answer"
    async with anyio.create_task_group() as group:
        group.start_soon(serve_pipe, requests, answers, answer)
        group.start_soon(pump, link, from_upstream)
        try:
            said = await call(upstream, name, {"a": 1})
        except UpstreamFailure as exc:
            said = str(exc)
        group.cancel_scope.cancel()
    return said


async def through_session(answer: Answer, name: str = "tool") -> types.CallToolResult | str:
    to_upstream, requests = anyio.create_memory_object_stream[Any](16)
    answers, from_upstream = anyio.create_memory_object_stream[Any](16)
    said: types.CallToolResult | str = "no answer"
    async with anyio.create_task_group() as group, ClientSession(from_upstream, to_upstream) as session:
        group.start_soon(serve_session, requests, answers, answer)
        upstream = Upstream("up", session, 5.0, 5.0)
        try:
            said = await call(upstream, name, {"a": 1})
        except UpstreamFailure as exc:
            said = str(exc)
        group.cancel_scope.cancel()
    return said


class Unnegotiated:
    """A session before its handshake (no version: the SDK's default one)."""

    protocol_version = None


JSON = st.recursive(st.none() | st.booleans() | st.integers(-5, 5) | st.text(max_size=5),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                                 max_size=3), max_leaves=6)
BLOCK = st.one_of(
    st.fixed_dictionaries({"type": st.just("text"), "text": st.text(max_size=8)}),
    st.fixed_dictionaries({"type": st.just("image"), "data": st.sampled_from(["aGk=", "not base64!"]),
                           "mimeType": st.just("image/png")}),
    st.dictionaries(st.sampled_from(["type", "text", "uri", "x"]), JSON, max_size=3))
RESULT = st.fixed_dictionaries({}, optional={
    "content": st.lists(BLOCK, max_size=3) | JSON, "isError": st.booleans() | JSON,
    "structuredContent": st.dictionaries(st.text(max_size=4), JSON, max_size=2) | JSON,
    "_meta": st.dictionaries(st.text(max_size=4), JSON, max_size=2), "ttlMs": st.integers(-3, 3),
    "resultType": st.sampled_from(["complete", "input_required"]), "extra": JSON})
ERROR = st.fixed_dictionaries({"code": st.integers(-32700, 5), "message": st.text(max_size=8)},
                              optional={"data": JSON})


@settings(max_examples=80, deadline=None)
@given(said=st.one_of(RESULT.map(lambda r: {"result": r}), ERROR.map(lambda e: {"error": e})))
def test_an_answer_read_off_the_pipe_is_what_the_sdks_session_makes_of_it(said: dict[str, Any]) -> None:
    """Differential: the result (or the failure, its text included) the proxy gets for one upstream answer is the
    same whether the answer is read off the upstream's pipe or by the SDK's client session."""

    async def answer(request: dict[str, Any]) -> dict[str, Any]:
        return {"jsonrpc": "2.0", "id": request["id"], **said}

    raw = anyio.run(through_link, answer)
    sdk = anyio.run(through_session, answer)
    assert raw == sdk


def test_a_malformed_answer_is_an_error_naming_the_upstream() -> None:
    async def answer(request: dict[str, Any]) -> dict[str, Any]:
        return {"jsonrpc": "2.0", "id": request["id"], "result": {"content": "not a list of blocks"}}

    said = anyio.run(through_link, answer)
    assert isinstance(said, str) and said.startswith("upstream 'up' answered a malformed result")


def test_an_answer_with_no_result_object_is_an_error_naming_the_upstream() -> None:
    async def answer(request: dict[str, Any]) -> dict[str, Any]:
        return {"jsonrpc": "2.0", "id": request["id"], "result": ["a", "list"]}

    said = anyio.run(through_link, answer)
    assert isinstance(said, str) and said.startswith("upstream 'up' answered a malformed result")


def test_concurrent_calls_on_one_upstream_each_get_their_own_answer_in_any_order() -> None:
    """Several sessions' calls in flight on one upstream, answered last first: each call its own result."""
    to_upstream, requests = anyio.create_memory_object_stream[bytes](16)
    answers, from_upstream = anyio.create_memory_object_stream[bytes](16)
    link = Link(Stdin(to_upstream))  # type: ignore[arg-type]
    upstream = Upstream("up", Unnegotiated(), 5.0, 5.0, link=link)  # type: ignore[arg-type]
    arrived = anyio.Event()
    seen: list[str] = []

    async def answer(request: dict[str, Any]) -> dict[str, Any]:
        seen.append(request["id"])
        if len(seen) == 5:
            arrived.set()
        await arrived.wait()
        await anyio.sleep(0.01 * (5 - seen.index(request["id"])))  # the last to come, answered first
        text = str(request["params"]["arguments"]["n"])
        return {"jsonrpc": "2.0", "id": request["id"], "result": {"content": [{"type": "text", "text": text}]}}

    async def run() -> dict[int, str]:
        got: dict[int, str] = {}

        async def one(n: int) -> None:
            result = await call(upstream, "tool", {"n": n})
            got[n] = result.content[0].text  # type: ignore[union-attr]

        async with anyio.create_task_group() as group:
            group.start_soon(serve_pipe, requests, answers, answer)
            group.start_soon(pump, link, from_upstream)
            async with anyio.create_task_group() as calls:
                for n in range(5):
                    calls.start_soon(one, n)
            group.cancel_scope.cancel()
        return got

    assert anyio.run(run) == {n: str(n) for n in range(5)}
    assert len(set(seen)) == 5


def test_an_upstream_whose_pipe_ends_fails_the_call_in_flight_as_gone() -> None:
    async def answer(request: dict[str, Any]) -> None:
        return None

    async def run() -> str:
        to_upstream, requests = anyio.create_memory_object_stream[bytes](16)
        answers, from_upstream = anyio.create_memory_object_stream[bytes](16)
        link = Link(Stdin(to_upstream))  # type: ignore[arg-type]
        upstream = Upstream("up", Unnegotiated(), 5.0, 5.0, link=link)  # type: ignore[arg-type]
        async with anyio.create_task_group() as group:
            group.start_soon(pump, link, from_upstream)

            async def end() -> None:
                await requests.receive()
                await answers.aclose()
            group.start_soon(end)
            try:
                await call(upstream, "tool", {})
            except UpstreamFailure as exc:
                assert upstream.gone is not None
                return str(exc)
        raise AssertionError("answered")

    assert anyio.run(run) == "upstream 'up' is gone: Connection closed"


HANDSHAKE = [
    {"jsonrpc": "2.0", "id": 0, "method": "initialize", "params": {
        "protocolVersion": "2025-11-25", "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}}},
    {"jsonrpc": "2.0", "method": "notifications/initialized"},
]


async def no_call(name: str, arguments: dict[str, Any]) -> types.CallToolResult:
    raise AssertionError("called")


class Wire:
    """The proxy's side of the client's wire: what it wrote."""

    def __init__(self) -> None:
        self.written: list[dict[str, Any]] = []

    async def write(self, text: str) -> None:
        self.written.append(json.loads(text))


@pytest.mark.parametrize(("message", "taken"), [
    ({"name": "get_order", "arguments": {"order_id": "A1"}}, True),
    ({"name": "get_order"}, True),
    ({"name": "get_order", "arguments": {}, "_meta": {"progressToken": 1}}, False),  # the SDK's: its _meta
    ({"name": 3, "arguments": {}}, False),  # the SDK says what is wrong with it
    ({"name": "get_order", "arguments": []}, False),
])
def test_only_a_plain_call_after_the_handshake_is_answered_beside_the_sdk(message: dict[str, Any],
                                                                         taken: bool) -> None:
    calls: list[tuple[str, dict[str, Any]]] = []

    async def proxy_call(name: str, arguments: dict[str, Any]) -> types.CallToolResult:
        calls.append((name, arguments))
        return types.CallToolResult(content=[types.TextContent(text="done")])

    request = {"jsonrpc": "2.0", "id": 7, "method": "tools/call", "params": message}

    async def run() -> tuple[list[str], Wire]:
        wire = Wire()
        reader = fastpath.Lines(wire, proxy_call)  # type: ignore[arg-type]
        sdk: list[str] = []
        for line in [*HANDSHAKE, request]:
            reader.feed((json.dumps(line) + "\n").encode())
            while reader.queued:  # what the SDK reads, in order
                sdk.append(await anext(reader))
                if json.loads(sdk[-1]).get("method") == "initialize":  # the SDK's answer, as it writes it
                    await reader.watched().write(json.dumps({"jsonrpc": "2.0", "id": 0, "result": {
                        "protocolVersion": "2025-11-25", "capabilities": {},
                        "serverInfo": {"name": "p", "version": "1"}}}) + "\n")
        reader.end()
        sdk += [line async for line in reader]
        while reader.in_flight:
            await anyio.sleep(0)
        return sdk, wire

    sdk, wire = anyio.run(run)
    assert len(sdk) == (2 if taken else 3)  # the handshake always reaches the SDK
    if taken:
        assert calls == [("get_order", dict(message.get("arguments") or {}))]
        assert wire.written[-1] == {"jsonrpc": "2.0", "id": 7, "result": {
            "content": [{"type": "text", "text": "done"}], "isError": False}}
    else:
        assert calls == [] and len(wire.written) == 1


def test_no_call_is_answered_beside_the_sdk_before_the_handshake() -> None:
    async def run() -> list[str]:
        reader = fastpath.Lines(Wire(), no_call)  # type: ignore[arg-type]
        call = {"jsonrpc": "2.0", "id": 1, "method": "tools/call", "params": {"name": "x"}}
        reader.feed((json.dumps(call) + "\n").encode())
        reader.end()
        return [line async for line in reader]

    assert len(anyio.run(run)) == 1


async def handshaken(wire: Wire, proxy_call: fastpath.Call) -> fastpath.Lines:
    """The agent's lines with the handshake done (the SDK's `initialize` answer written as it writes it)."""
    reader = fastpath.Lines(wire, proxy_call)  # type: ignore[arg-type]
    for line in HANDSHAKE:
        reader.feed((json.dumps(line) + "\n").encode())
        if line is HANDSHAKE[0]:  # `initialize`
            await anext(reader)
            await reader.watched().write(json.dumps({"jsonrpc": "2.0", "id": 0, "result": {
                "protocolVersion": "2025-11-25", "capabilities": {}, "serverInfo": {"name": "p", "version": "1"}}}))
    await anext(reader)
    return reader


@pytest.mark.parametrize("ending", ["cancelled", "closed"])
def test_a_call_the_agent_cancels_has_no_answer_and_one_in_flight_at_the_end_is_answered_closed(
        ending: str) -> None:
    """A `notifications/cancelled` ends the call's task with no answer (the spec); the wire closing while a call is
    in flight answers it `Connection closed`, as the SDK answers its own."""
    stopped: list[str] = []

    async def hanging(name: str, arguments: dict[str, Any]) -> types.CallToolResult:
        try:
            await anyio.sleep_forever()
        finally:
            stopped.append(name)
        raise AssertionError("answered")

    async def run() -> Wire:
        wire = Wire()
        reader = await handshaken(wire, hanging)
        call = {"jsonrpc": "2.0", "id": 7, "method": "tools/call", "params": {"name": "get_order"}}
        reader.feed((json.dumps(call) + "\n").encode())
        await anyio.sleep(0.01)
        assert list(reader.in_flight) == [7]
        if ending == "cancelled":
            reader.feed((json.dumps({"jsonrpc": "2.0", "method": "notifications/cancelled",
                                     "params": {"requestId": 7}}) + "\n").encode())
            await anyio.sleep(0.01)
        else:
            await reader.close()
        assert not reader.in_flight
        return wire

    written = anyio.run(run).written[1:]  # after the SDK's answer to `initialize`
    assert stopped == ["get_order"]
    if ending == "cancelled":
        assert written == []
    else:
        assert written == [{"jsonrpc": "2.0", "id": 7, "error": {"code": types.CONNECTION_CLOSED,
                                                                 "message": "Connection closed"}}]


def test_answers_cut_anywhere_into_reads_are_each_their_calls() -> None:
    """The upstream's stdout read in pieces of any size: two answers in one read, one answer over many."""
    to_upstream, requests = anyio.create_memory_object_stream[bytes](16)
    answers, from_upstream = anyio.create_memory_object_stream[bytes](16)
    link = Link(Stdin(to_upstream))  # type: ignore[arg-type]
    upstream = Upstream("up", Unnegotiated(), 5.0, 5.0, link=link)  # type: ignore[arg-type]

    async def upstream_side() -> None:
        said = b""
        for _ in range(3):
            request = json.loads(await requests.receive())
            text = "x" * 100 + str(request["params"]["arguments"]["n"])
            said += (json.dumps({"jsonrpc": "2.0", "id": request["id"], "result": {
                "content": [{"type": "text", "text": text}]}}) + "\n").encode()
        cuts = [0, 7, 8, 150, len(said) - 5, len(said)]
        for start, end in itertools.pairwise(cuts):
            await answers.send(said[start:end])

    async def run() -> list[str]:
        got: dict[int, str] = {}

        async def one(n: int) -> None:
            result = await call(upstream, "tool", {"n": n})
            got[n] = result.content[0].text  # type: ignore[union-attr]

        async with anyio.create_task_group() as group:
            group.start_soon(upstream_side)
            group.start_soon(pump, link, from_upstream)
            async with anyio.create_task_group() as calls:
                for n in range(3):
                    calls.start_soon(one, n)
            group.cancel_scope.cancel()
        return [got[n] for n in range(3)]

    assert anyio.run(run) == ["x" * 100 + str(n) for n in range(3)]


def test_two_writers_on_the_wire_never_interleave_their_messages() -> None:
    """The SDK's writer and a call's answer at once, each larger than the pipe holds: each line arrives whole."""
    outbound, sink = os.pipe()
    os.set_blocking(sink, False)
    os.set_blocking(outbound, False)
    messages = [json.dumps({"n": n, "pad": str(n) * (3 << 20)}) + "\n" for n in range(3)]

    async def run() -> list[str]:
        writer = pipes.PipeWriter(sink)
        lines = fastpath.Lines(Wire(), no_call)  # type: ignore[arg-type]
        reader = pipes.LineReader(lines.feed, lines.end, "the wire")
        async with anyio.create_task_group() as group, pipes.reading(outbound, reader):
            for message in messages:
                group.start_soon(writer.write, message)
            return [await anext(lines) for _ in messages]

    try:
        assert sorted(anyio.run(run)) == sorted(messages)
    finally:
        os.close(sink)
        os.close(outbound)
