"""`tools/call` on the stdio wire, answered without the SDK's server dispatch.

The SDK's server costs about a millisecond of CPU a call: a pydantic parse of each line into a message, memory
streams between its reader, dispatcher and writer, a task and a context per request, and a dump of the answer.
Here the client's lines are read as the SDK's `stdio_server` reads them (`Lines` is the stream it iterates), and a
`tools/call` request of the plainest shape (`{"name": str, "arguments": object}` and nothing else) on a
connection whose handshake is done is taken off it: the proxy's `call` answers it in a task of its own, and the
answer is serialized as the SDK serializes a `tools/call` result (the negotiated version's result schema, the
same JSON-RPC envelope) or an error (`MCPError` as its own error, anything else as the SDK's catch-all), written
on the same wire.

Everything else, an odd `tools/call` included, goes to the SDK as it came: the handshake (whose answer, as the SDK
writes it, says which version was negotiated), `tools/list`, pings, notifications. A `notifications/cancelled` for
a call answered here ends its task with no answer (the spec: none is sent for a cancelled request); when the client
closes the wire, a call still in flight is answered `Connection closed`, as the SDK answers its own.
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import suppress
from typing import TYPE_CHECKING, Any

import anyio
import mcp_types as types
from anyio.abc import TaskGroup
from mcp.shared.dispatcher import coerce_request_id
from mcp.shared.jsonrpc_dispatcher import cancelled_request_id_from_params, handler_exception_to_error_data
from mcp_types import methods
from mcp_types.version import HANDSHAKE_PROTOCOL_VERSIONS
from pydantic import ValidationError

if TYPE_CHECKING:
    from precond_client.mcp.stdio import PipeWriter

logger = logging.getLogger(__name__)
Call = Callable[[str, dict[str, Any]], Awaitable[types.CallToolResult]]
"""The proxy's `tools/call` of the stdio session: a tool's name and arguments → its result (or `MCPError`)."""
SHUTDOWN_WRITE = 2.0
"""Seconds the `Connection closed` answer of a call in flight at the end may take to write."""


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
    """The client's lines as the SDK's `stdio_server` iterates them, less the calls answered here."""

    def __init__(self, lines: AsyncIterator[str], writer: PipeWriter, call: Call, group: TaskGroup) -> None:
        self.lines = lines
        self.writer = writer
        self.call = call
        self.group = group
        self.handshake = Handshake()
        self.in_flight: dict[Any, anyio.CancelScope] = {}

    def __aiter__(self) -> Lines:
        return self

    async def __anext__(self) -> str:
        while True:
            line = await anext(self.lines)
            if not self._taken(line):
                return line

    def watched(self) -> Watched:
        return Watched(self.writer, self.handshake)

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
            self.group.start_soon(self._answer, message["id"], message["params"])
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
        scope = self.in_flight.get(coerce_request_id(request_id)) if request_id is not None else None
        if scope is not None:
            scope.cancel()

    async def _answer(self, request_id: int | str, params: dict[str, Any]) -> None:
        key = coerce_request_id(request_id)
        scope = self.in_flight[key] = anyio.CancelScope()
        try:
            with scope:
                try:
                    text = _response(request_id, self.handshake.version or "", await self.call(
                        params["name"], dict(params.get("arguments") or {})))
                except Exception as exc:
                    text = _error(request_id, exc)
        except anyio.get_cancelled_exc_class():  # the wire closed: answered as the SDK answers its own
            with anyio.CancelScope(shield=True), anyio.move_on_after(SHUTDOWN_WRITE), suppress(OSError):
                await self.writer.write(_error(request_id, types.ErrorData(
                    code=types.CONNECTION_CLOSED, message="Connection closed")))
            raise
        finally:
            if self.in_flight.get(key) is scope:
                del self.in_flight[key]
        if scope.cancelled_caught:  # the client cancelled it: no answer
            return
        with suppress(OSError):
            await self.writer.write(text)


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
    response = types.JSONRPCResponse(jsonrpc="2.0", id=request_id, result=dumped)
    return response.model_dump_json(by_alias=True, exclude_unset=True) + "\n"


def _error(request_id: int | str, failure: Exception | types.ErrorData) -> str:
    """An error's line as the SDK's dispatcher writes it (code 0 and the text for an exception not MCP's)."""
    error = failure if isinstance(failure, types.ErrorData) else handler_exception_to_error_data(failure)
    if error is None:
        logger.exception("handler for 'tools/call' raised")
        error = types.ErrorData(code=0, message=str(failure))
    response = types.JSONRPCError(jsonrpc="2.0", id=request_id, error=error)
    return response.model_dump_json(by_alias=True, exclude_unset=True) + "\n"
