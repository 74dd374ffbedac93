"""A connection handed out without redis-py's read (precond/patches/redis_checkout.py)
still never answers a command with
a reply meant for another, and a connection the server closed is still replaced before it is used; against a
real redis-server."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from redis._parsers.hiredis import _AsyncHiredisParser
from redis.asyncio import Redis

from precond.patches.redis_checkout import check_out_without_read
from precond.stack.local import RedisServer


def run(redis_server: RedisServer, body: Callable[[Redis[bytes]], Awaitable[Any]]) -> Any:
    check_out_without_read()
    check_out_without_read()  # a second call changes nothing

    async def main() -> Any:
        redis: Redis[bytes] = Redis.from_url(redis_server.url, socket_timeout=5)
        try:
            await redis.set("k", b"mine")
            return await body(redis)
        finally:
            await redis.aclose()  # type: ignore[attr-defined]

    return asyncio.run(main())


def test_a_reply_left_on_a_connection_is_never_read_as_the_next_one(redis_server: RedisServer) -> None:
    async def body(redis: Redis[bytes]) -> list[bytes | None]:
        pool = redis.connection_pool
        connection = await pool.get_connection()
        await connection.send_command("ECHO", b"stale")  # its reply is never read
        await pool.release(connection)
        await asyncio.sleep(0.1)  # the stale reply has reached the client
        return [await redis.get("k") for _ in range(3)]

    assert run(redis_server, body) == [b"mine"] * 3


def test_a_connection_the_server_closed_is_replaced_before_use(redis_server: RedisServer) -> None:
    async def body(redis: Redis[bytes]) -> list[bytes | None]:
        ids = [await redis.client_id() for _ in range(2)]
        assert ids[0] == ids[1]  # one pooled connection, used twice
        killer: Redis[bytes] = Redis.from_url(redis_server.url)
        await killer.client_kill_filter(_id=ids[0])
        await killer.aclose()  # type: ignore[attr-defined]
        await asyncio.sleep(0.1)  # the server's FIN has reached the client
        answers = [await redis.get("k") for _ in range(2)]
        assert await redis.client_id() != ids[0]
        return answers

    assert run(redis_server, body) == [b"mine"] * 2


def test_an_idle_healthy_connection_is_handed_out_without_a_read(redis_server: RedisServer,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    reads: list[object] = []
    read: Any = _AsyncHiredisParser.can_read_destructive

    async def counted(self: _AsyncHiredisParser) -> bool:
        reads.append(self)
        answer: bool = await read(self)
        return answer

    monkeypatch.setattr(_AsyncHiredisParser, "can_read_destructive", counted)

    async def body(redis: Redis[bytes]) -> list[bytes | None]:
        assert len(reads) == 1  # the connection's first use: connected, then read as redis-py does
        return [await redis.get("k") for _ in range(5)]

    assert run(redis_server, body) == [b"mine"] * 5
    assert len(reads) == 1
