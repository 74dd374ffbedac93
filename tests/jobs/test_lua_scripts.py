"""Scripts run by digest (precond.jobs.scripts) against a real redis-server: a Redis that lost its scripts (a restart,
SCRIPT FLUSH) still runs them, from their text."""

from __future__ import annotations

import asyncio

from redis.asyncio import Redis

from precond.jobs.scripts import LuaScript
from precond.stack.local import RedisServer

INCREMENT = LuaScript("return redis.call('INCRBY', KEYS[1], ARGV[1])")


def test_a_script_runs_by_digest_and_again_after_redis_forgot_it(redis_server: RedisServer) -> None:
    async def main() -> None:
        redis: Redis[bytes] = Redis.from_url(redis_server.url)
        try:
            assert await INCREMENT(redis, ["n"], [2]) == 2  # unknown to this Redis: sent as text, kept
            assert (await redis.script_exists(INCREMENT.sha)) == [True]
            assert await INCREMENT(redis, ["n"], [3]) == 5  # by digest
            await redis.script_flush()
            assert await INCREMENT(redis, ["n"], [1]) == 6
        finally:
            await redis.aclose()  # type: ignore[attr-defined]

    asyncio.run(main())
