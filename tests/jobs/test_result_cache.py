"""The gateway's memory of results it read (precond/jobs/cache.py, `recent_bytes`): a repeated read costs no round
trip to Redis, the memory stays within its bound however small or large the results, and an entry this
deployment did not sign is never kept; against a real redis-server."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from redis.asyncio import Redis

from precond.jobs.cache import RECENT_ENTRY_BYTES, RECENT_ENTRY_OVERHEAD, ResultCache
from precond.jobs.queue.keys import cache_key
from precond.stack.local import RedisServer

SECRET = b"s" * 32


def run(redis_server: RedisServer, recent_bytes: int, body: Callable[[ResultCache, Redis[bytes]], Awaitable[Any]]
        ) -> Any:
    async def main() -> Any:
        redis: Redis[bytes] = Redis.from_url(redis_server.url)
        try:
            return await body(ResultCache(redis, ttl_s=3600, secret=SECRET, recent_bytes=recent_bytes), redis)
        finally:
            await redis.aclose()  # type: ignore[attr-defined]

    return asyncio.run(main())


def _gets(redis_server: RedisServer) -> int:
    return int(redis_server.client().info("commandstats").get("cmdstat_get", {}).get("calls", 0))


def test_a_result_read_once_is_read_again_without_redis(redis_server: RedisServer) -> None:
    async def body(cache: ResultCache, redis: Redis[bytes]) -> list[Any]:
        await cache.put("check-a", {"results": [1]})
        answers = [await cache.get("check-a") for _ in range(5)]
        await redis.delete(cache_key("check-a"))  # what an eviction does: the kept copy still answers
        return [*answers, await cache.get("check-a"), await cache.get("check-b")]

    assert run(redis_server, 1 << 20, body) == [{"results": [1]}] * 6 + [None]
    assert _gets(redis_server) == 2  # the first read of a and the miss of b


def test_without_the_memory_every_read_asks_redis(redis_server: RedisServer) -> None:
    async def body(cache: ResultCache, redis: Redis[bytes]) -> list[Any]:
        await cache.put("check-a", {"results": [1]})
        return [await cache.get("check-a") for _ in range(3)]

    assert run(redis_server, 0, body) == [{"results": [1]}] * 3
    assert _gets(redis_server) == 3


def test_the_memory_stays_within_its_bound(redis_server: RedisServer) -> None:
    bound = 64 * 1024

    async def body(cache: ResultCache, redis: Redis[bytes]) -> tuple[int, int]:
        await cache.put("check-large", {"pad": "x" * RECENT_ENTRY_BYTES})
        await cache.get("check-large")
        for i in range(2_000):  # tiny results: their keys and bookkeeping count too
            await cache.put(f"check-{i}", {})
            await cache.get(f"check-{i}")
        kept = cache._recent
        assert kept is not None and cache_key("check-large") not in kept
        return kept.currsize, len(kept)

    size, entries = run(redis_server, bound, body)
    assert size <= bound
    assert entries <= bound // RECENT_ENTRY_OVERHEAD


def test_an_entry_not_signed_by_this_deployment_is_never_kept(redis_server: RedisServer) -> None:
    async def body(cache: ResultCache, redis: Redis[bytes]) -> list[Any]:
        await redis.set(cache_key("check-f"), b'v1.0000.{"results": ["forged"]}')
        first = await cache.get("check-f")
        await cache.put("check-f", {"results": ["real"]})
        return [first, await cache.get("check-f")]

    assert run(redis_server, 1 << 20, body) == [None, {"results": ["real"]}]
