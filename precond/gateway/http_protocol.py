"""The gateway's HTTP/1.1 protocol: uvicorn's httptools (llhttp, C) implementation with a bound on the request
head, which httptools does not have.

h11 (pure Python) took about an eighth of the gateway's CPU per check and was kept only for its bounded head
buffer. httptools accumulates the URL and every header value for as long as the client sends them (uvicorn
joins the URL's pieces with `+=`, httptools a value's pieces the same way: quadratic in the number of reads).
So a head is refused with the server's plain-text 400 and the connection closed when, still incomplete, it has
taken more than `MAX_REQUEST_HEAD_BYTES` (one read more at most) or `MAX_REQUEST_HEAD_READS` reads, or when,
complete, its URL and headers pass `MAX_REQUEST_HEAD_BYTES`: the same bound whatever the segmentation (h11
checked only a head that arrived over several reads). Within the bound every head reaches the app, which
answers with its own JSON error.

The subclass overrides and reads uvicorn's protocol internals; where this uvicorn lacks one of them, the gateway
speaks h11 instead (`GatewayHttpProtocol`, with a log line): slower, with h11's own bound on an incomplete head.
"""

from __future__ import annotations

import asyncio
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from precond import patches

MAX_REQUEST_HEAD_BYTES = 128 * 1024
"""URL and headers of one request; the longest head a legitimate client of this API sends is a few KiB."""

MAX_URL_BYTES = 65535
"""httptools' own bound: its URL parser keeps offsets in 16 bits, and uvicorn answers a longer URL with its 400."""

MAX_REQUEST_HEAD_READS = 256
"""Reads one incomplete head may take: bounds the quadratic joining above to 256 x 128 KiB of copying."""

HEAD_TOO_LARGE = "Request head too large."


class HeadTooLarge(ValueError):
    """Raised inside the parser's callback: httptools stops, uvicorn answers 400 and closes."""


class HeadWithBody:
    """The connection's transport, holding a response's head until its body is written, to the end of the loop's
    turn at most, so that both leave in one write: uvicorn writes the head when the app starts the response
    and the body when it sends it, two `send` system calls and two TCP segments a request, where the gateway's
    answers (a few hundred bytes, sent at once) need one. A quarter of the gateway's CPU per check, sampled,
    was these writes.

    Everything else is the transport's own (`__getattr__`); what would put bytes after the head, or end the
    connection, writes the head first."""

    def __init__(self, transport: asyncio.Transport) -> None:
        self._transport = transport
        self._head = b""

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if self._head:
            data, self._head = self._head + bytes(data), b""
        elif data[:9] == b"HTTP/1.1 " and data[-4:] == b"\r\n\r\n":
            self._head = bytes(data)
            asyncio.get_running_loop().call_soon(self.flush)  # a body that is not sent at once (a stream, HEAD)
            return
        self._transport.write(data)

    def flush(self) -> None:
        if self._head:
            head, self._head = self._head, b""
            if not self._transport.is_closing():
                self._transport.write(head)

    def writelines(self, lines: Any) -> None:
        self.flush()
        self._transport.writelines(lines)

    def write_eof(self) -> None:
        self.flush()
        self._transport.write_eof()

    def close(self) -> None:
        self.flush()
        self._transport.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


class BoundedHttpToolsProtocol(HttpToolsProtocol):
    _in_head = False
    _head_bytes = 0
    _head_reads = 0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(HeadWithBody(transport))  # type: ignore[arg-type]

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head, self._head_bytes, self._head_reads = True, 0, 0

    def on_headers_complete(self) -> None:
        self._in_head = False
        size = len(self.url) + sum(len(name) + len(value) for name, value in self.headers)
        if size > MAX_REQUEST_HEAD_BYTES:
            raise HeadTooLarge(f"{size} bytes")
        super().on_headers_complete()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if not self._in_head or self.transport.is_closing():
            return
        self._head_bytes += len(data)  # the whole read: it began or continued this head
        self._head_reads += 1
        if self._head_bytes > MAX_REQUEST_HEAD_BYTES or self._head_reads > MAX_REQUEST_HEAD_READS:
            self.logger.warning(HEAD_TOO_LARGE)
            self.send_400_response(HEAD_TOO_LARGE)


def _needs() -> list[str]:
    """What the subclass overrides and reads of uvicorn's httptools protocol."""
    protocol = ("uvicorn.protocols.http.httptools_impl", "HttpToolsProtocol")
    return (patches.missing(*protocol, "on_message_begin", "on_headers_complete", "data_received",
                            "send_400_response", "connection_made")
            + patches.unassigned(*protocol, "on_message_begin", "url", "headers")
            + patches.unassigned(*protocol, "connection_made", "transport", "logger"))


def _chosen() -> type[Any]:
    if patches.apply("request heads bounded in httptools' protocol", _needs(), lambda: None, instead="h11"):
        return BoundedHttpToolsProtocol
    return H11Protocol


GatewayHttpProtocol = _chosen()
"""The protocol uvicorn runs (`--http precond.gateway.http_protocol:GatewayHttpProtocol`)."""
