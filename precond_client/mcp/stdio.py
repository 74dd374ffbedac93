"""The proxy's stdio, read and written on the event loop itself. The SDK's `stdio_server` reads and writes the
process's stdin and stdout through `anyio.wrap_file`: each line read, written and flushed is a hop to a worker
thread and back, three a call, which on a busy machine cost more than the proxy's own work. Here the wire is two
non-blocking pipe descriptors: the loop's read callback cuts the client's into lines (`pipes.LineReader`), each
handed to `fastpath.Lines`, which answers the plain `tools/call` requests beside the SDK and queues the rest for
the same `stdio_server`, which iterates them as its stdin; both write with one `os.write` a message. Anything else
(a file, a terminal) is left to the SDK as it is.

As the SDK does, the wire is moved off fd 0 and 1 while the proxy serves (fd 0 reads the null device, fd 1 writes
to stderr), so a stray `print` or a child that inherits them never writes into the protocol; both come back when
it ends.
"""

from __future__ import annotations

import fcntl
import os
import stat
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, contextmanager, suppress
from typing import Any, cast

import anyio
from mcp.server.stdio import stdio_server

from precond_client.mcp import fastpath
from precond_client.mcp.fastpath import Call
from precond_client.mcp.pipes import LineReader, PipeWriter, reading


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
            lines = fastpath.Lines(PipeWriter(wire_out), call)
            reader = LineReader(lines.feed, lines.end, "the client's connection")
            lines.pause = reader.pause
            try:
                async with reading(wire_in, reader), \
                        stdio_server(cast(Any, lines), cast(Any, lines.watched())) as streams:
                    yield streams
            finally:
                with anyio.CancelScope(shield=True):
                    await lines.close()  # the wire closed: the calls still in flight answered so
    finally:
        os.close(null)
