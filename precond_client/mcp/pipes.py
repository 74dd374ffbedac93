"""Pipes read and written on the event loop itself, for the proxy's two stdio wires (the client's, `stdio`, and
each command upstream's, `link`).

A pipe is read by the loop's own read callback (`LineReader`, an asyncio protocol): each line goes to its
consumer as the read that completes it returns, with no task woken and no stream between them, which on a call's
path saves a turn of the loop per message against an anyio stream. A line is written with one `os.write` when the
pipe takes it (`PipeWriter`), again with no turn of the loop (an anyio byte stream yields to the loop after each
send).
"""

from __future__ import annotations

import asyncio
import os
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from typing import cast

import anyio

MAX_LINE = 1 << 28
"""Bytes a message may have before its newline (256 MiB): past it the pipe is read no further (its connection
ends, as at its end of input), said on stderr."""


class LineReader(asyncio.Protocol):
    """A pipe cut into lines as the loop reads it: each (bytes, its newline kept; a last line without one too) to
    `line`, in order, then `end()` once, when the pipe ends or is closed. `pause(True)` stops reading until
    `pause(False)`, for a consumer that is behind."""

    def __init__(self, line: Callable[[bytes], None], end: Callable[[], None], source: str) -> None:
        self.line = line
        self.end = end
        self.source = source
        """How the message past `MAX_LINE` names the pipe ("the client's connection")."""
        self.buffer = bytearray()
        self.transport: asyncio.ReadTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.ReadTransport, transport)

    def close(self) -> None:
        """The pipe read no further (`end` follows)."""
        if self.transport is not None:
            self.transport.close()

    def pause(self, paused: bool) -> None:
        if self.transport is not None and not self.transport.is_closing():
            (self.transport.pause_reading if paused else self.transport.resume_reading)()

    def data_received(self, data: bytes) -> None:
        searched = len(self.buffer)  # a long line's earlier chunks are not searched again
        self.buffer += data
        start, end = 0, self.buffer.find(b"\n", searched)
        while end >= 0:
            self.line(bytes(self.buffer[start: end + 1]))
            start, end = end + 1, self.buffer.find(b"\n", end + 1)
        del self.buffer[:start]
        if len(self.buffer) > MAX_LINE:
            print(f"precond mcp: a message of more than {MAX_LINE} bytes without a newline: {self.source} is read "
                  "no further", file=sys.stderr, flush=True)
            self.buffer.clear()
            assert self.transport is not None
            self.transport.close()

    def eof_received(self) -> bool:
        if self.buffer:
            self.line(bytes(self.buffer))
            self.buffer.clear()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self.end()


@asynccontextmanager
async def reading(fd: int, reader: LineReader) -> AsyncIterator[LineReader]:
    """`fd` (a pipe) read by `reader` on the loop until it ends or the block does (the loop reads a duplicate of
    it, closed at the end: `fd` itself is the caller's to close)."""
    pipe = os.fdopen(os.dup(fd), "rb", buffering=0)
    transport, _ = await asyncio.get_running_loop().connect_read_pipe(lambda: reader, pipe)
    try:
        yield reader
    finally:
        transport.close()


class PipeWriter:
    """`await write(text)` on a non-blocking descriptor, whole (`flush` has nothing left to do). Two writers (on
    the client's wire, the SDK's and the calls answered beside it) never interleave: a message the pipe cannot
    take at once is finished under a lock the next message waits for."""

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

    def close(self) -> None:
        """The descriptor closed, once (the reader's end of input); a later write fails as on a closed file."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
