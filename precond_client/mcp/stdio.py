"""The proxy's stdio, read and written on the event loop itself. The SDK's `stdio_server` reads and writes the
process's stdin and stdout through `anyio.wrap_file`: each line read, written and flushed is a hop to a worker
thread and back, three a call, which on a busy machine cost more than the proxy's own work. Here the wire is two
non-blocking pipe descriptors the loop waits on, handed to the same `stdio_server` as its streams, less the plain
`tools/call` requests, which `fastpath` answers beside it on the same wire; anything else (a file, a terminal) is
left to the SDK as it is.

As the SDK does, the wire is moved off fd 0 and 1 while the proxy serves (fd 0 reads the null device, fd 1 writes
to stderr), so a stray `print` or a child that inherits them never writes into the protocol; both come back when
it ends.
"""

from __future__ import annotations

import fcntl
import os
import stat
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, contextmanager, suppress
from typing import Any, cast

import anyio
from mcp.server.stdio import stdio_server

from precond_client.mcp import fastpath
from precond_client.mcp.fastpath import Call

READ_BYTES = 1 << 16
MAX_LINE = 1 << 28
"""Bytes a message may have before its newline (256 MiB): past it the wire is read no further (the client's
connection ends, as at its end of input), said on stderr."""


class PipeLines:
    """The lines of a non-blocking descriptor, as `async for line in stdin` reads them (UTF-8, bad bytes
    replaced, as the SDK reads them)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buffer = bytearray()

    def __aiter__(self) -> PipeLines:
        return self

    async def __anext__(self) -> str:
        while True:
            end = self.buffer.find(b"\n")
            if end >= 0:
                line = bytes(self.buffer[: end + 1])
                del self.buffer[: end + 1]
                return line.decode("utf-8", "replace")
            if len(self.buffer) > MAX_LINE:
                print(f"precond mcp: a message of more than {MAX_LINE} bytes without a newline: the client's "
                      "connection is read no further", file=sys.stderr, flush=True)
                raise StopAsyncIteration
            try:
                chunk = os.read(self.fd, READ_BYTES)
            except BlockingIOError:
                await anyio.wait_readable(self.fd)
                continue
            if not chunk:
                if not self.buffer:
                    raise StopAsyncIteration
                line = bytes(self.buffer)
                self.buffer.clear()
                return line.decode("utf-8", "replace")
            self.buffer += chunk


class PipeWriter:
    """`await write(text)` on a non-blocking descriptor, whole (`flush` has nothing left to do). Two writers (the
    SDK's and the calls answered beside it) never interleave: a message the pipe cannot take at once is finished
    under a lock the next message waits for."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.lock = anyio.Lock()

    async def write(self, text: str) -> None:
        data = memoryview(text.encode("utf-8"))
        if not self.lock.locked():
            with suppress(BlockingIOError):
                data = data[os.write(self.fd, data):]
            if not data:
                return
        async with self.lock:
            while data:
                try:
                    data = data[os.write(self.fd, data):]
                except BlockingIOError:
                    await anyio.wait_writable(self.fd)

    async def flush(self) -> None:
        return None


def _is_pipe(fd: int) -> bool:
    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


@contextmanager
def _claimed(fd: int, diversion: int) -> Any:
    """A private, non-blocking duplicate of `fd` (the wire), with `fd` itself pointed at `diversion` until the
    block ends; the wire's flags and `fd` are restored then."""
    wire = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 3)
    flags = fcntl.fcntl(wire, fcntl.F_GETFL)
    fcntl.fcntl(wire, fcntl.F_SETFL, flags | os.O_NONBLOCK)
    os.dup2(diversion, fd)
    try:
        yield wire
    finally:
        os.dup2(wire, fd)
        with suppress(OSError):
            fcntl.fcntl(wire, fcntl.F_SETFL, flags)
        os.close(wire)


@asynccontextmanager
async def serving_stdio(call: Call) -> AsyncIterator[tuple[Any, Any]]:
    """The SDK's `stdio_server` streams, over the loop's own pipe reads and writes when fd 0 and 1 are pipes, with
    the plain `tools/call` requests answered by `call` beside the SDK (`fastpath`)."""
    if not (_is_pipe(0) and _is_pipe(1)):
        async with stdio_server() as streams:
            yield streams
        return
    null = os.open(os.devnull, os.O_RDONLY)
    try:
        with _claimed(0, null) as wire_in, _claimed(1, 2) as wire_out:
            async with anyio.create_task_group() as calls:
                lines = fastpath.Lines(PipeLines(wire_in), PipeWriter(wire_out), call, calls)
                async with stdio_server(cast(Any, lines), cast(Any, lines.watched())) as streams:
                    yield streams
                calls.cancel_scope.cancel()  # the wire closed: the calls still in flight answered so
    finally:
        os.close(null)
