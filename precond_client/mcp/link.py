"""A stdio upstream's pipes, shared by the SDK's `ClientSession` and the proxy's own `tools/call` requests.

The SDK's client stack costs about a millisecond of CPU a call (a pydantic parse of every line, a memory-stream
hop to its reader, its dispatcher's pending table and task per request). Here the upstream's process is started
as the SDK's `stdio_client` starts it (the safe part of the environment, its own process group, stderr passed
on) and its stdout read on the loop: a line that answers one of the proxy's `request`s (a string id the SDK's
integer ids never take) goes straight to its waiter as parsed JSON; every other line (the handshake, `tools/list`,
the upstream's notifications and requests) is parsed and handed to the `ClientSession` as `stdio_client` does.
The session's own messages are written, whole, on the same pipe.

`request` keeps the SDK's `send_request` contract: `MCPError` with `REQUEST_TIMEOUT` past the timeout (after
telling the upstream the request is cancelled), `CONNECTION_CLOSED` once the upstream's stdout ended or its stdin
broke, and the upstream's own error response as it is.
"""

from __future__ import annotations

import json
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from dataclasses import dataclass
from typing import Any

import anyio
import mcp_types as types
from anyio.abc import Process
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream
from mcp.client.stdio import get_default_environment
from mcp.shared.exceptions import MCPError
from mcp.shared.message import SessionMessage

from precond_client.mcp.sdk_private import stop_server_process

CLOSED = types.ErrorData(code=types.CONNECTION_CLOSED, message="Connection closed")
PREFIX = "precond-"
"""The proxy's own request ids: `precond-1`, ... (a string: the SDK's session numbers its requests)."""


@dataclass
class Waiter:
    done: anyio.Event
    answer: dict[str, Any] | None = None


class Link:
    """One upstream process's stdin and stdout (`stdio_link` makes it and runs its reader)."""

    def __init__(self, process: Process) -> None:
        self.process = process
        self.waiting: dict[str, Waiter] = {}
        self.count = 0
        self.closed = False

    async def request(self, method: str, params: dict[str, Any], timeout: float) -> dict[str, Any]:
        """The upstream's `result` for one request, or `MCPError` as the SDK's `send_request` raises it."""
        if self.closed:
            raise MCPError(CLOSED.code, CLOSED.message)
        self.count += 1
        request_id = f"{PREFIX}{self.count}"
        waiter = self.waiting[request_id] = Waiter(anyio.Event())
        try:
            line = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
            try:
                await self._write(json.dumps(line, ensure_ascii=False, separators=(",", ":")))
            except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
                raise MCPError(CLOSED.code, CLOSED.message) from None
            with anyio.move_on_after(timeout) as waited:
                await waiter.done.wait()
            if waited.cancelled_caught:
                await self._cancel(request_id, f"timed out after {timeout}s", shield=False)
                raise MCPError(types.REQUEST_TIMEOUT, f"Request {method!r} timed out")
        except anyio.get_cancelled_exc_class():
            await self._cancel(request_id, "caller cancelled", shield=True)
            raise
        finally:
            self.waiting.pop(request_id, None)
        return _outcome(waiter.answer)

    async def _cancel(self, request_id: str, reason: str, *, shield: bool) -> None:
        """The courtesy `notifications/cancelled` the SDK sends for a request it stopped waiting for."""
        note = {"jsonrpc": "2.0", "method": "notifications/cancelled",
                "params": {"requestId": request_id, "reason": reason}}
        with anyio.CancelScope(shield=shield), anyio.move_on_after(1.0), \
                suppress(anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
            await self._write(json.dumps(note, separators=(",", ":")))

    async def _write(self, text: str) -> None:
        """One message on the upstream's stdin: a single write of the whole line, so two never interleave."""
        assert self.process.stdin is not None
        await self.process.stdin.send((text + "\n").encode("utf-8"))

    async def read(self, session: MemoryObjectSendStream[SessionMessage | Exception]) -> None:
        """The upstream's stdout until it ends: answers to `request`s to their waiters, the rest to the session
        (once the session is gone, read and dropped, so an upstream flushing its output can still exit)."""
        assert self.process.stdout is not None
        buffer = bytearray()
        try:
            async with session:
                with suppress(anyio.EndOfStream, anyio.ClosedResourceError, anyio.BrokenResourceError, OSError):
                    while True:
                        searched = len(buffer)  # a long line's earlier chunks are not searched again
                        buffer += await self.process.stdout.receive()
                        end = buffer.find(b"\n", searched)
                        while end >= 0:
                            line = bytes(buffer[:end])
                            del buffer[: end + 1]
                            if not self._answered(line):
                                with suppress(anyio.ClosedResourceError, anyio.BrokenResourceError):
                                    await session.send(_parsed(line))
                            end = buffer.find(b"\n")
        finally:
            self.closed = True
            for waiter in self.waiting.values():
                waiter.done.set()  # no answer: the connection closed

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
        waiter.answer = message
        waiter.done.set()
        return True

    async def write(self, session: MemoryObjectReceiveStream[SessionMessage]) -> None:
        """The session's messages, serialized as `stdio_client` serializes them."""
        async with session:
            try:
                async for message in session:
                    await self._write(message.message.model_dump_json(by_alias=True, exclude_unset=True))
            except (anyio.ClosedResourceError, anyio.BrokenResourceError, OSError):
                return


def _parsed(line: bytes) -> SessionMessage | Exception:
    try:
        return SessionMessage(types.jsonrpc_message_adapter.validate_json(line, by_name=False))
    except ValueError as exc:
        return exc


def _outcome(answer: dict[str, Any] | None) -> dict[str, Any]:
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
    """The upstream started as `stdio_client` starts it: the `ClientSession`'s streams and the `Link`; stopped
    as `stdio_client` stops it (stdin closed, a grace period, then its process group ended)."""
    process = await anyio.open_process(argv, env=get_default_environment(), stderr=sys.stderr,
                                       start_new_session=True)
    link = Link(process)
    to_session, read = anyio.create_memory_object_stream[SessionMessage | Exception](0)
    write, from_session = anyio.create_memory_object_stream[SessionMessage](0)
    async with anyio.create_task_group() as group:
        group.start_soon(link.read, to_session)
        group.start_soon(link.write, from_session)
        try:
            yield read, write, link
        finally:
            with anyio.CancelScope(shield=True):
                read.close()
                write.close()
                link.closed = True
                await stop_server_process(process)
            group.cancel_scope.cancel()
