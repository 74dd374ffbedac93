"""Commands packed by hiredis (precond/patches/redis_packing.py)
are the bytes redis-py's own packer wrote, and values it
refused are still refused; a real redis-server reads them back as sent."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from redis._parsers.encoders import Encoder
from redis.asyncio import Redis
from redis.asyncio.connection import Connection
from redis.connection import PythonRespSerializer  # type: ignore[attr-defined]  # types-redis predates it
from redis.exceptions import DataError

from precond.jobs.scripts import LuaScript
from precond.patches.redis_packing import pack_with_hiredis
from precond.stack.local import RedisServer

ECHO = LuaScript("return ARGV")


def test_the_packed_bytes_are_redis_py_s_own() -> None:
    """Against redis-py's Python packer (`PythonRespSerializer`, the asyncio connection's algorithm), which
    this process may already have replaced on the asyncio connection."""
    python = PythonRespSerializer(6000, Encoder("utf-8", "strict", False).encode)  # type: ignore[no-untyped-call]
    pack_with_hiredis()
    pack_with_hiredis()  # a second call changes nothing
    connection = Connection()
    for args in (("CONFIG GET", "maxmemory"), ("EVALSHA", "f" * 40, 2, "k1", b"k2", 0.1, -7, "h\u00e9", b"")):
        assert b"".join(connection.pack_command(*args)) == b"".join(python.pack(*args))
    assert connection.pack_command("SET", "k", "h\u00e9llo", 0.1, 2**70, b"\x00\xff") == [
        b"*6\r\n$3\r\nSET\r\n$1\r\nk\r\n$6\r\nh\xc3\xa9llo\r\n$3\r\n0.1\r\n$22\r\n1180591620717411303424\r\n"
        b"$2\r\n\x00\xff\r\n"
    ]
    refused_values: tuple[Any, ...] = (True, None, object())
    for refused in refused_values:
        with pytest.raises(DataError):
            connection.pack_command("SET", "k", refused)


def test_redis_reads_back_what_was_sent(redis_server: RedisServer) -> None:
    pack_with_hiredis()
    values = ["h\u00e9llo", b"\x00\xff\r\n", 7, 0.25, "", "x" * 100_000]

    async def main() -> list[bytes]:
        redis: Redis[bytes] = Redis.from_url(redis_server.url)
        try:
            await redis.hincrbyfloat("counts", "seconds", 0.125)
            await redis.hincrbyfloat("counts", "seconds", 0.125)
            assert await redis.hget("counts", "seconds") == b"0.25"
            answer: list[bytes] = await ECHO(redis, [], values)
            return answer
        finally:
            await redis.aclose()  # type: ignore[attr-defined]

    assert asyncio.run(main()) == ["h\u00e9llo".encode(), b"\x00\xff\r\n", b"7", b"0.25", b"", b"x" * 100_000]
