"""The versioned tenant store (precond/store/tenant_store.py) that precondition sets and trained policies share,
against a redis-server of the test's own: versions in order only, each bound refused with its own code and
nothing written, a retried job finding its own version, the bytes given back on delete, another tenant seeing
nothing."""

from __future__ import annotations

from redis.asyncio import Redis

from precond.stack.local import RedisServer
from precond.store import tenant_store as store
from precond.store.tenant_store import POLICIES, SETS, Bounds

BOUNDS = Bounds(records=2, versions=3, tenant_bytes=100)



def test_versions_are_stored_in_order_within_the_bounds(redis_server: RedisServer) -> None:
    async def scenario(redis: Redis[bytes]) -> None:
        assert await store.put(redis, SETS, "t", "a", 2, "x", BOUNDS) == store.MISSING
        assert await store.put(redis, SETS, "t", "a", 1, "v1", BOUNDS, beside={"summary": "s1"}) == 1
        assert await store.put(redis, SETS, "t", "a", 1, "again", BOUNDS) == store.CONFLICT
        assert await store.put(redis, SETS, "t", "a", 3, "v3", BOUNDS) == store.CONFLICT
        assert await store.put(redis, SETS, "t", "a", 2, "v2", BOUNDS, beside={"summary": "s2"}) == 2
        assert await store.put(redis, SETS, "t", "a", 3, "v3", BOUNDS) == 3
        assert await store.put(redis, SETS, "t", "a", 4, "v4", BOUNDS) == store.TOO_MANY_VERSIONS
        assert await store.latest(redis, SETS, "t", "a") == 3
        assert await store.read(redis, SETS, "t", "a", 1) == b"v1"
        assert await redis.hget(SETS.record_key("t", "a"), "summary") == b"s2"
        assert await store.put(redis, SETS, "t", "b", 1, "b" * 95, BOUNDS) == store.TOO_MANY_BYTES
        assert await store.put(redis, SETS, "t", "b", 1, "b", BOUNDS) == 1
        assert await store.put(redis, SETS, "t", "c", 1, "c", BOUNDS) == store.TOO_MANY_RECORDS
        assert await store.ids(redis, SETS, "t") == ["a", "b"] and await store.used_bytes(redis, SETS, "t") == 7
        assert await store.latest(redis, SETS, "other", "a") is None and await store.ids(redis, SETS, "other") == []
        assert await store.put(redis, SETS, "u", "c", 1, "c" * 1000, Bounds(1, 1, 0)) == 1  # 0: no byte bound

    redis_server.run(scenario)


def test_a_retried_job_finds_its_version_and_delete_gives_the_bytes_back(redis_server: RedisServer) -> None:
    async def scenario(redis: Redis[bytes]) -> None:
        weights = {"weights": b"\x00" * 50}
        assert await store.put(redis, POLICIES, "t", "p", 1, "{}", BOUNDS, job="j1", parts=weights) == 1
        assert await store.put(redis, POLICIES, "t", "p", 1, "{}", BOUNDS, job="j1", parts=weights) == 1
        assert await store.put(redis, POLICIES, "t", "p", 1, "{}", BOUNDS, job="j2", parts=weights) == store.CONFLICT
        assert await store.put(redis, POLICIES, "t", "p", 2, "{}", BOUNDS, job="j3",
                               parts=weights) == store.TOO_MANY_BYTES  # the weights count: 52 + 52 > 100
        assert await store.read(redis, POLICIES, "t", "p", 1, "weights") == b"\x00" * 50
        assert await store.used_bytes(redis, POLICIES, "t") == 52
        assert await store.count(redis, POLICIES, "t") == 1
        assert await store.delete(redis, POLICIES, "t", "p")
        assert not await store.delete(redis, POLICIES, "t", "p")
        assert await store.used_bytes(redis, POLICIES, "t") == 0 and await store.count(redis, POLICIES, "t") == 0

    redis_server.run(scenario)
