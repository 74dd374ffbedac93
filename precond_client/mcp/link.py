"""A stdio upstream's pipes, shared by the SDK's `ClientSession` and the proxy's own `tools/call` requests.

The SDK's client stack costs about a millisecond of CPU a call (a pydantic parse of every line, a memory-stream
hop to its reader, its dispatcher's pending table and task per request). Here the upstream's process is started
as the SDK's `stdio_client` starts it (the safe part of the environment, its own process group, stderr passed
on), but on pipes of the proxy's own, read and written on the loop (`pipes`): a line that answers one of the
proxy's `request`s (a string id the SDK's integer ids never take) goes from the loop's read callback straight to
its waiter as parsed JSON; every other line (the handshake, `tools/list`, the upstream's notifications and
requests) is parsed and handed to the `ClientSession` as `stdio_client` does, in order, by a task of its own. The
session's own messages are written, whole, on the same pipe. The process is stopped as `stdio_client` stops it
(`sdk_private.stop_piped_process`).

`request` keeps the SDK's `send_request` contract: `MCPError` with `REQUEST_TIMEOUT` past the timeout (after
telling the upstream the request is cancelled), `CONNECTION_CLOSED` once the upstream's stdout ended or its stdin
broke, and the upstream's own error response as it is.
"""

from __future__ import annotations

import asyncio
import json
import os
import shlex
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from typing import Any

import anyio
import mcp_types as types
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream
from mcp.client.stdio import get_default_environment
from mcp.shared.exceptions import MCPError
from mcp.shared.message import SessionMessage

from precond_client.mcp.pipes import LineReader, PipeWriter, reading
from precond_client.mcp.sdk_private import stop_piped_process

CLOSED = types.ErrorData(code=types.CONNECTION_CLOSED, message="Connection closed")
PREFIX = "precond-"
"""The proxy's own request ids: `precond-1`, ... (a string: the SDK's session numbers its requests)."""
BACKLOG = 64
"""Lines the session may be behind the upstream's stdout before it is read no further until it catches up."""


Answer = dict[str, Any] | None
"""A request's answer as read (None: the connection closed first)."""
TIMED_OUT: dict[str, Any] = {}
"""What a request's waiter is given when its timeout passes (never an answer: those are read, new, objects)."""


def _expire(waiter: asyncio.Future[Answer]) -> None:
    if not waiter.done():
        waiter.set_result(TIMED_OUT)


class Link:
    """One upstream process's stdin (`writer`) and stdout (each line `received`, then `ended`)."""

    def __init__(self, writer: PipeWriter) -> None:
        self.writer = writer
        self.waiting: dict[str, asyncio.Future[Answer]] = {}
        self.count = 0
        self.closed = False
        self.backlog: asyncio.Queue[bytes | None] = asyncio.Queue()
        """The lines for the session, in order (None: the upstream's stdout ended)."""
        self.pause: Callable[[bool], None] = _ignored
        """Set by the stdout's reader: True stops reading while the session is `BACKLOG` lines behind."""

    async def request(self, method: str, params: dict[str, Any], timeout: float) -> dict[str, Any]:
        """The upstream's `result` for one request, or `MCPError` as the SDK's `send_request` raises it."""
        if self.closed:
            raise MCPError(CLOSED.code, CLOSED.message)
        self.count += 1
        request_id = f"{PREFIX}{self.count}"
        loop = asyncio.get_running_loop()
        waiter = self.waiting[request_id] = loop.create_future()
        try:
            line = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
            try:
                await self._write(json.dumps(line, ensure_ascii=False, separators=(",", ":")))
            except OSError:
                raise MCPError(CLOSED.code, CLOSED.message) from None
            timer = loop.call_later(timeout, _expire, waiter)  # a plain future and timer: no cancel scope a call
            try:
                answer = await waiter
            finally:
                timer.cancel()
            if answer is TIMED_OUT:
                await self._cancel(request_id, f"timed out after {timeout}s", shield=False)
                raise MCPError(types.REQUEST_TIMEOUT, f"Request {method!r} timed out")
        except anyio.get_cancelled_exc_class():
            await self._cancel(request_id, "caller cancelled", shield=True)
            raise
        finally:
            self.waiting.pop(request_id, None)
        return _outcome(answer)

    async def _cancel(self, request_id: str, reason: str, *, shield: bool) -> None:
        """The courtesy `notifications/cancelled` the SDK sends for a request it stopped waiting for."""
        note = {"jsonrpc": "2.0", "method": "notifications/cancelled",
                "params": {"requestId": request_id, "reason": reason}}
        with anyio.CancelScope(shield=shield), anyio.move_on_after(1.0), suppress(OSError):
            await self._write(json.dumps(note, separators=(",", ":")))

    async def _write(self, text: str) -> None:
        """One message on the upstream's stdin: a single write of the whole line, so two never interleave."""
        await self.writer.write(text + "\n")

    def received(self, line: bytes) -> None:
        """A line of the upstream's stdout: an answer to its waiter, anything else queued for the session (a last
        line without its newline is dropped, as `stdio_client` drops it)."""
        if not line.endswith(b"\n") or self._answered(line):
            return
        self.backlog.put_nowait(line)
        if self.backlog.qsize() == BACKLOG:
            self.pause(True)

    def ended(self) -> None:
        """The upstream's stdout ended: each request in flight fails as closed, the session's stream ends."""
        self.closed = True
        for waiter in self.waiting.values():
            if not waiter.done():
                waiter.set_result(None)  # no answer: the connection closed
        self.backlog.put_nowait(None)

    def _answered(self, line: bytes) -> bool:
        if not self.waiting or PREFIX.encode() not in line:
            return False
        try:
            message = json.loads(line)
        except ValueError:
            return False
        if not isinstance(message, dict) or "method" in message:
            return False
        request_id = message.get("id")
        waiter = self.waiting.get(request_id) if isinstance(request_id, str) else None
        if waiter is None:
            return False
        if not waiter.done():
            waiter.set_result(message)
        return True

    async def forward(self, session: MemoryObjectSendStream[SessionMessage | Exception]) -> None:
        """The upstream's other lines to the session, parsed as `stdio_client` parses them, until its stdout ends
        (once the session is gone, read and dropped, so an upstream flushing its output can still exit)."""
        async with session:
            while (line := await self.backlog.get()) is not None:
                if self.backlog.qsize() == BACKLOG - 1:
                    self.pause(False)
                with suppress(anyio.ClosedResourceError, anyio.BrokenResourceError):
                    await session.send(_parsed(line))

    async def write(self, session: MemoryObjectReceiveStream[SessionMessage]) -> None:
        """The session's messages, serialized as `stdio_client` serializes them."""
        async with session:
            try:
                async for message in session:
                    await self._write(message.message.model_dump_json(by_alias=True, exclude_unset=True))
            except (anyio.ClosedResourceError, anyio.BrokenResourceError, OSError):
                return


def _ignored(paused: bool) -> None:
    return None


def _parsed(line: bytes) -> SessionMessage | Exception:
    try:
        return SessionMessage(types.jsonrpc_message_adapter.validate_json(line, by_name=False))
    except ValueError as exc:
        return exc


def _outcome(answer: Answer) -> dict[str, Any]:
    """The `result` of an answer; its error as `MCPError`; no answer (the connection closed) as CONNECTION_CLOSED.
    An answer that is neither is a malformed result (`ValueError`)."""
    if answer is None:
        raise MCPError(CLOSED.code, CLOSED.message)
    if "error" in answer and "result" not in answer:
        raise MCPError.from_error_data(types.ErrorData.model_validate(answer["error"]))
    result = answer.get("result")
    if not isinstance(result, dict):
        raise ValueError(f"an answer with no result object: {json.dumps(answer)[:200]}")
    return result


@asynccontextmanager
async def stdio_link(argv: list[str]) -> AsyncIterator[tuple[Any, Any, Link]]:
    """The upstream started as `stdio_client` starts it, on the proxy's own pipes: the `ClientSession`'s streams
    and the `Link`; stopped as `stdio_client` stops it (stdin closed, a grace period, then its process group
    ended)."""
    child_in, stdin = os.pipe()
    stdout, child_out = os.pipe()
    try:
        process = await anyio.open_process(argv, stdin=child_in, stdout=child_out, env=get_default_environment(),
                                           stderr=sys.stderr, start_new_session=True)
    except BaseException:
        os.close(stdin)
        os.close(stdout)
        raise
    finally:
        os.close(child_in)
        os.close(child_out)
    os.set_blocking(stdin, False)
    link = Link(PipeWriter(stdin))
    reader = LineReader(link.received, link.ended, f"the upstream {shlex.join(argv)[:200]!r}")
    link.pause = reader.pause
    to_session, read = anyio.create_memory_object_stream[SessionMessage | Exception](0)
    write, from_session = anyio.create_memory_object_stream[SessionMessage](0)
    try:
        async with reading(stdout, reader), anyio.create_task_group() as group:
            group.start_soon(link.forward, to_session)
            group.start_soon(link.write, from_session)
            try:
                yield read, write, link
            finally:
                with anyio.CancelScope(shield=True):
                    read.close()
                    write.close()
                    link.closed = True
                    await stop_piped_process(process, link.writer.close, reader.close)
                group.cancel_scope.cancel()
    finally:
        link.writer.close()
        os.close(stdout)
