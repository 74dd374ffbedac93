"""Frames between a child and its fork server, and between the server and the worker.

Child → server: a stream of length-prefixed JSON frames (``%08x`` + body): ``phase`` (what runs now, for
error messages), ``begin``/``unit`` around each independently judged part (one candidate, one proposed
call), and one ``end``. The server trusts none of it: it checks order, indices and sizes, and keeps the
units it already has when a child dies, so one runaway part fails alone.

Server → child: a header line ``{"skip", "size", "keep"}`` (the units an earlier child of the call settled, the
body's length, whether the child waits for another request after this one), then the body.

Server → worker: a header line ``{"id", "status", ...}`` echoing the request's id, then the body.
"""

from __future__ import annotations

import json
import os
import typing

LENGTH_CHARS = 8
CHUNK = 1 << 16
"""Bytes asked of one read of a pipe. A pipe holds 64 KiB, so a larger read returns no more, yet `os.read`
allocates all of it first: 1 MiB (mapped and unmapped at every read) cost ~30 µs a read against ~2 µs, on
every frame of the guard's hot path."""


def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def read_request(fd: int) -> tuple[dict[str, typing.Any], bytes] | None:
    """The server's next request to a child: its header line (`skip`, `size`, `keep`) and `size` bytes of body;
    None at end of input. Nothing follows a request until the child has answered it, so nothing is over-read."""
    data = bytearray()
    while b"\n" not in data:
        chunk = os.read(fd, CHUNK)
        if not chunk:
            return None
        data += chunk
    line, _, rest = bytes(data).partition(b"\n")
    header = json.loads(line)
    body = bytearray(rest)
    while len(body) < int(header["size"]):
        chunk = os.read(fd, CHUNK)
        if not chunk:
            return None
        body += chunk
    return header, bytes(body)


def encode_frame(frame: dict[str, object]) -> bytes:
    body = json.dumps(frame).encode("ascii")
    return b"%08x" % len(body) + body


def split_frames(buffer: bytearray, cap: int) -> typing.Iterator[dict[str, typing.Any]]:
    """Complete frames at the front of `buffer` (consumed); ValueError when the stream is malformed."""
    while len(buffer) >= LENGTH_CHARS:
        size = int(bytes(buffer[:LENGTH_CHARS]), 16)
        if size > cap:
            raise ValueError("frame larger than the result limit")
        if len(buffer) < LENGTH_CHARS + size:
            return
        frame = json.loads(bytes(buffer[LENGTH_CHARS:LENGTH_CHARS + size]))
        del buffer[:LENGTH_CHARS + size]
        if not isinstance(frame, dict):
            raise ValueError("frame is not an object")
        yield frame


class Reporter:
    """The child's side of the stream; a budget keeps a hostile result from filling the server.

    A unit's result waits to be written with the frame that follows it (the next `begin`, a `phase` or the
    `end`): one write where there were two, and one wake-up of the server fewer. Nothing untrusted runs
    between a unit's result and that frame (untrusted code runs only after a `phase` or a `begin`, which are
    written at once), so a child that dies loses no result it had."""

    def __init__(self, fd: int | None, cap: int) -> None:
        self._fd, self._left = fd, cap
        self._pending = b""

    def _send(self, frame: dict[str, object], wait: bool = False) -> None:
        if self._fd is None:
            return
        data = encode_frame(frame)
        self._left -= len(data)
        if self._left < 0:
            write_all(self._fd, self._pending + encode_frame({"t": "end", "result": {"error": {
                "kind": "limit", "limit": "result", "message": "result larger than the result limit"}}}))
            os._exit(0)
        if wait:
            self._pending += data
            return
        write_all(self._fd, self._pending + data)
        self._pending = b""

    def phase(self, where: str) -> None:
        self._send({"t": "phase", "where": where})

    def begin(self, unit: int, where: str) -> None:
        self._send({"t": "begin", "unit": unit, "where": where})

    def unit(self, unit: int, result: dict[str, object]) -> None:
        self._send({"t": "unit", "unit": unit, "result": result}, wait=True)

    def end(self, result: dict[str, object]) -> None:
        self._send({"t": "end", "result": result})
        self._fd = None
