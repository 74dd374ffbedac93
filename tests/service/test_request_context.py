"""The gateway's outer middleware (service.middleware.RequestContext) lets the event loop serve other requests
before it handles one, even a request answered without waiting on anything (a result kept in memory, a token
of a lease, a refusal already known): answered at once, such requests kept uvicorn from reading some
connections for hundreds of milliseconds while others were served."""

from __future__ import annotations

import asyncio

from starlette.types import Message, Receive, Scope, Send

from precond.gateway.middleware import RequestContext
from precond.gateway.prometheus import Metrics


async def _answered_from_memory(scope: Scope, receive: Receive, send: Send) -> None:
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": b"{}"})


def _scope() -> Scope:
    return {"type": "http", "method": "POST", "path": "/check-actions", "headers": [], "state": {}}


async def _receive() -> Message:
    return {"type": "http.request", "body": b"{}", "more_body": False}


def test_a_burst_of_requests_answered_from_memory_does_not_hold_the_loop() -> None:
    app = RequestContext(_answered_from_memory, Metrics())
    answered: list[int] = []

    async def request(number: int) -> None:
        async def send(message: Message) -> None:
            if message["type"] == "http.response.body":
                answered.append(number)

        await app(_scope(), _receive, send)

    async def next_in_line() -> int:  # e.g. a connection's read, scheduled after the burst
        return len(answered)

    async def main() -> list[int]:
        burst = [asyncio.create_task(request(n)) for n in range(10)]
        seen = asyncio.create_task(next_in_line())
        await asyncio.gather(*burst)
        return [await seen, len(answered)]

    assert asyncio.run(main()) == [0, 10]  # it ran before the first of the burst was answered
