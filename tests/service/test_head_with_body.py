"""An answer's head and body leave the gateway in one write (`http_protocol.HeadWithBody`), and a head whose body
does not follow at once (a stream, a HEAD request) still leaves by the end of the event loop's turn."""

from __future__ import annotations

import asyncio
from typing import Any

from precond.gateway.http_protocol import HeadWithBody

HEAD = b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\n"


class Recorded:
    """A transport that records its writes."""

    def __init__(self) -> None:
        self.writes: list[bytes] = []
        self.closed = False

    def write(self, data: Any) -> None:
        self.writes.append(bytes(data))

    def is_closing(self) -> bool:
        return self.closed

    def close(self) -> None:
        self.closed = True

    def get_extra_info(self, name: str) -> str:
        return f"extra {name}"


def test_a_head_and_its_body_are_one_write() -> None:
    async def run() -> list[bytes]:
        recorded = Recorded()
        transport = HeadWithBody(recorded)  # type: ignore[arg-type]
        transport.write(HEAD)
        transport.write(b"{}")
        await asyncio.sleep(0)
        return recorded.writes

    assert asyncio.run(run()) == [HEAD + b"{}"]


def test_a_head_alone_leaves_by_the_end_of_the_turn_and_before_a_close() -> None:
    async def run() -> tuple[list[bytes], list[bytes], list[bytes], bool]:
        recorded = Recorded()
        transport = HeadWithBody(recorded)  # type: ignore[arg-type]
        transport.write(HEAD)
        held = list(recorded.writes)
        await asyncio.sleep(0)
        after_turn = list(recorded.writes)
        transport.write(HEAD)
        transport.close()
        return held, after_turn, recorded.writes, recorded.closed

    held, after_turn, after_close, closed = asyncio.run(run())
    assert held == [] and after_turn == [HEAD] and after_close == [HEAD, HEAD] and closed


def test_everything_else_is_the_transports_own() -> None:
    async def run() -> tuple[list[bytes], str]:
        recorded = Recorded()
        transport = HeadWithBody(recorded)  # type: ignore[arg-type]
        transport.write(b"a chunk of a stream")
        return recorded.writes, transport.get_extra_info("peername")

    assert asyncio.run(run()) == ([b"a chunk of a stream"], "extra peername")
