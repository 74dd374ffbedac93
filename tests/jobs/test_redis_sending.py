"""A command written without redis-py's task (precond/patches/redis_sending.py)
is still bounded by the socket timeout when
Redis stops reading, still arrives whole when it is larger than the socket takes at once, and a connection the
server closed still fails or reconnects as with redis-py's own send; against a real redis-server."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from redis import exceptions
from redis.asyncio import Redis

from precond.patches.redis_checkout import check_out_without_read
from precond.patches.redis_sending import send_without_task
from precond.stack.local import RedisServer


def run(url: str, body: Callable[[Redis[bytes]], Awaitable[Any]], timeout_s: float = 5) -> Any:
    send_without_task()
    send_without_task()  # a second call changes nothing
    check_out_without_read()  # as the gateway and the worker run

    async def main() -> Any:
        redis: Redis[bytes] = Redis.from_url(url, socket_timeout=timeout_s)
        try:
            return await body(redis)
        finally:
            await redis.aclose()  # type: ignore[attr-defined]

    return asyncio.run(main())


def test_a_command_the_socket_takes_whole_makes_no_task(redis_server: RedisServer,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    waits: list[object] = []
    wait_for = asyncio.wait_for

    async def counted(awaitable: Any, timeout: float | None) -> Any:
        waits.append(awaitable)
        return await wait_for(awaitable, timeout)

    monkeypatch.setattr(asyncio, "wait_for", counted)

    async def body(redis: Redis[bytes]) -> list[bytes | None]:
        await redis.set("k", b"v")  # the first command connects through redis-py's own send
        del waits[:]
        return [await redis.get("k") for _ in range(20)]

    assert run(redis_server.url, body) == [b"v"] * 20
    assert waits == []


def test_a_command_larger_than_the_socket_takes_at_once_arrives_whole(redis_server: RedisServer) -> None:
    value = os.urandom(48 * 1024 * 1024)

    async def body(redis: Redis[bytes]) -> bool:
        await redis.ping()
        await redis.set("big", value)
        return await redis.get("big") == value

    assert run(redis_server.url, body)


def test_a_redis_that_stops_reading_times_the_write_out(tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    assert server.process is not None
    value = os.urandom(64 * 1024 * 1024)  # far more than the two sockets' buffers hold

    async def body(redis: Redis[bytes]) -> float:
        await redis.ping()
        os.kill(server.process.pid, signal.SIGSTOP)  # type: ignore[union-attr]
        started = time.monotonic()
        try:
            with pytest.raises(exceptions.TimeoutError):
                await redis.set("big", value)
        finally:
            os.kill(server.process.pid, signal.SIGCONT)  # type: ignore[union-attr]
        return time.monotonic() - started

    try:
        assert run(server.url, body, timeout_s=1) < 10
    finally:
        server.stop()


def test_a_connection_the_server_closed_fails_or_reconnects_as_before(redis_server: RedisServer) -> None:
    async def body(redis: Redis[bytes]) -> list[bytes | None]:
        await redis.set("k", b"v")
        first = await redis.client_id()
        killer: Redis[bytes] = Redis.from_url(redis_server.url)
        await killer.client_kill_filter(_id=first)
        await killer.aclose()  # type: ignore[attr-defined]
        await asyncio.sleep(0.1)
        answers = [await redis.get("k") for _ in range(3)]
        assert await redis.client_id() != first
        return answers

    assert run(redis_server.url, body) == [b"v"] * 3
