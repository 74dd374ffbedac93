"""`tools/call` on the stdio wire, answered without the SDK's server dispatch.

The SDK's server costs about a millisecond of CPU a call: a pydantic parse of each line into a message, memory
streams between its reader, dispatcher and writer, a task and a context per request, and a dump of the answer.
Here each line of the client's wire is handed to `Lines.feed` as the loop reads it, parsed once, and a
`tools/call` request of the plainest shape (`{"name": str, "arguments": object}` and nothing else) on a
connection whose handshake is done is kept from the SDK: the proxy's `call` answers it in a task of its own
(started from the read itself, no turn of the loop in between), and the answer is serialized as the SDK
serializes a `tools/call` result (the negotiated version's result schema, the same JSON-RPC envelope) or an error
(`MCPError` as its own error, anything else as the SDK's catch-all), written on the same wire.

Everything else, an odd `tools/call` included, goes to the SDK as it came (`Lines` is the stream the SDK's
`stdio_server` iterates as its stdin, in the wire's order): the handshake (whose answer, as the SDK
writes it, says which version was negotiated), `tools/list`, pings, notifications. A `notifications/cancelled` for
a call answered here ends its task with no answer (the spec: none is sent for a cancelled request); when the client
closes the wire, a call still in flight is answered `Connection closed`, as the SDK answers its own.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from contextlib import suppress
from typing import TYPE_CHECKING, Any

import anyio
import mcp_types as types
import pydantic_core
from mcp.shared.dispatcher import coerce_request_id
from mcp.shared.jsonrpc_dispatcher import cancelled_request_id_from_params, handler_exception_to_error_data
from mcp_types import methods
from mcp_types.version import HANDSHAKE_PROTOCOL_VERSIONS
from pydantic import ValidationError

if TYPE_CHECKING:
    from precond_client.mcp.pipes import PipeWriter

logger = logging.getLogger(__name__)
Call = Callable[[str, dict[str, Any]], Awaitable[types.CallToolResult]]
"""The proxy's `tools/call` of the stdio session: a tool's name and arguments → its result (or `MCPError`)."""
SHUTDOWN_WRITE = 2.0
"""Seconds the `Connection closed` answer of a call in flight at the end may take to write."""
BACKLOG = 64
"""Lines the SDK may be behind the wire before the wire is read no further until it catches up."""


class Handshake:
    """What the SDK negotiated: the version of its `initialize` answer, and the client's `initialized`."""

    def __init__(self) -> None:
        self.asked: Any = None
        self.version: str | None = None
        self.initialized = False
        self.again = False
        """A second `initialize`: whatever the SDK makes of it, every later call is left to it."""

    @property
    def done(self) -> bool:
        return self.version is not None and self.initialized and not self.again

    def initialize(self, request_id: Any) -> None:
        self.again = self.again or self.asked is not None
        self.asked = request_id

    def written(self, text: str) -> None:
        """A message the SDK wrote: the answer to `initialize` gives the version."""
        if self.asked is None or self.version is not None:
            return
        try:
            message = json.loads(text)
        except ValueError:
            return
        result = message.get("result") if isinstance(message, dict) else None
        if isinstance(result, dict) and message.get("id") == self.asked:
            version = result.get("protocolVersion")
            self.version = version if version in HANDSHAKE_PROTOCOL_VERSIONS else None


class Watched:
    """The SDK's writer: the wire's, with each message shown to the handshake while it is not done."""

    def __init__(self, writer: PipeWriter, handshake: Handshake) -> None:
        self.writer = writer
        self.handshake = handshake

    async def write(self, text: str) -> None:
        if self.handshake.version is None:
            self.handshake.written(text)
        await self.writer.write(text)

    async def flush(self) -> None:
        return None


class Lines:
    """The client's lines, `feed` one at a time as the wire is read: the plain calls answered here, each in a task
    of its own; the SDK's `stdio_server` iterates the others (`async for`), in their order."""

    def __init__(self, writer: PipeWriter, call: Call) -> None:
        self.writer = writer
        self.call = call
        self.handshake = Handshake()
        self.in_flight: dict[Any, asyncio.Task[None]] = {}
        self.queued: deque[str] = deque()
        self.ended = False
        self.closing = False
        self.waiter: asyncio.Future[None] | None = None
        self.pause: Callable[[bool], None] = _ignored
        """Set by the wire's reader: True stops reading while the SDK is `BACKLOG` lines behind, False resumes."""

    def __aiter__(self) -> Lines:
        return self

    async def __anext__(self) -> str:
        while not self.queued:
            if self.ended:
                raise StopAsyncIteration
            self.waiter = asyncio.get_running_loop().create_future()
            try:
                await self.waiter
            finally:
                self.waiter = None
        if len(self.queued) == BACKLOG:
            self.pause(False)
        return self.queued.popleft()

    def feed(self, raw: bytes) -> None:
        """One line of the wire: answered here or queued for the SDK (UTF-8, bad bytes replaced, as the SDK reads
        them)."""
        line = raw.decode("utf-8", "replace")
        if self._taken(line):
            return
        self.queued.append(line)
        if len(self.queued) == BACKLOG:
            self.pause(True)
        self._wake()

    def end(self) -> None:
        """The wire ended: the SDK's iteration ends once it has the lines queued."""
        self.ended = True
        self._wake()

    def _wake(self) -> None:
        if self.waiter is not None and not self.waiter.done():
            self.waiter.set_result(None)

    def watched(self) -> Watched:
        return Watched(self.writer, self.handshake)

    async def close(self) -> None:
        """The calls still in flight once the SDK is done (the wire closed): each answered `Connection closed`."""
        self.closing = True
        tasks = list(self.in_flight.values())
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _taken(self, line: str) -> bool:
        """Whether the line is a call answered here (noting the handshake and cancellations on the way)."""
        try:
            message = json.loads(line)
        except ValueError:
            return False
        if not isinstance(message, dict):
            return False
        method = message.get("method")
        if method == "initialize":
            self.handshake.initialize(message.get("id"))
        elif method == "notifications/initialized":
            self.handshake.initialized = True
        elif method == "notifications/cancelled":
            self._cancel(message.get("params"))
        elif method == "tools/call" and self.handshake.done and self._plain(message):
            request_id = message["id"]
            task = asyncio.get_running_loop().create_task(self._answer(request_id, message["params"]))
            self.in_flight[coerce_request_id(request_id)] = task
            return True
        return False

    def _plain(self, message: dict[str, Any]) -> bool:
        request_id, params = message.get("id"), message.get("params")
        if message.keys() != {"jsonrpc", "id", "method", "params"} or message["jsonrpc"] != "2.0":
            return False
        if isinstance(request_id, bool) or not isinstance(request_id, int | str):
            return False
        if coerce_request_id(request_id) in self.in_flight or not isinstance(params, dict):
            return False
        if not params.keys() <= {"name", "arguments"} or not isinstance(params.get("name"), str):
            return False
        if not isinstance(params.get("arguments"), dict | None):
            return False
        assert self.handshake.version is not None
        try:
            methods.validate_client_request("tools/call", self.handshake.version, params)
        except (KeyError, ValueError):  # pydantic's ValidationError among them: the SDK says what is wrong
            return False
        return True

    def _cancel(self, params: Any) -> None:
        request_id = cancelled_request_id_from_params(params if isinstance(params, dict) else None)
        task = self.in_flight.get(coerce_request_id(request_id)) if request_id is not None else None
        if task is not None:
            task.cancel()

    async def _answer(self, request_id: int | str, params: dict[str, Any]) -> None:
        """The call's answer on the wire; none for a call the client cancelled (the spec: none is sent), and
        `Connection closed` for one still in flight when the wire closed, as the SDK answers its own."""
        try:
            try:
                text = _response(request_id, self.handshake.version or "", await self.call(
                    params["name"], dict(params.get("arguments") or {})))
            except Exception as exc:
                text = _error(request_id, exc)
        except asyncio.CancelledError:
            if self.closing:
                text = _error(request_id, types.ErrorData(code=types.CONNECTION_CLOSED, message="Connection closed"))
                with anyio.move_on_after(SHUTDOWN_WRITE), suppress(OSError):
                    await self.writer.write(text)
            return
        finally:
            key = coerce_request_id(request_id)
            if self.in_flight.get(key) is asyncio.current_task():
                del self.in_flight[key]
        with suppress(OSError):
            await self.writer.write(text)


def _ignored(paused: bool) -> None:
    return None


def _response(request_id: int | str, version: str, result: types.CallToolResult) -> str:
    """The answer's line as the SDK's server writes a `tools/call` result (`MCPError` as it fails an invalid
    one)."""
    dumped = result.model_dump(by_alias=True, mode="json", exclude_none=True)
    try:
        dumped = methods.serialize_server_result("tools/call", version, dumped)
    except ValidationError:
        logger.exception("handler for 'tools/call' returned an invalid result")
        return _error(request_id, types.ErrorData(code=types.INTERNAL_ERROR,
                                                  message="Handler returned an invalid result"))
    # the envelope the SDK's `JSONRPCResponse` dumps (its `result` a plain object), written without the model
    return pydantic_core.to_json({"jsonrpc": "2.0", "id": request_id, "result": dumped}).decode() + "\n"


def _error(request_id: int | str, failure: Exception | types.ErrorData) -> str:
    """An error's line as the SDK's dispatcher writes it (code 0 and the text for an exception not MCP's)."""
    error = failure if isinstance(failure, types.ErrorData) else handler_exception_to_error_data(failure)
    if error is None:
        logger.exception("handler for 'tools/call' raised")
        error = types.ErrorData(code=0, message=str(failure))
    response = types.JSONRPCError(jsonrpc="2.0", id=request_id, error=error)
    return response.model_dump_json(by_alias=True, exclude_unset=True) + "\n"
