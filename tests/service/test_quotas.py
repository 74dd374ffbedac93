"""The gateway's per-tenant and per-source limits against a real redis-server: what a flood costs the shared
Redis, and that the limits let a tenant through again once its bucket has a token."""

from __future__ import annotations

import asyncio

from arq.connections import ArqRedis
from redis.asyncio import ConnectionPool

from service.caller import Caller
from service.quotas import MAX_BLOCKED_SOURCES, AuthLimit, Quotas, _remember
from stack.local import RedisServer


def _quotas(server: RedisServer, rate: float, burst: int) -> Quotas:
    redis = ArqRedis(ConnectionPool.from_url(server.url))
    return Quotas(redis, rate, burst, max_jobs=4, auth=AuthLimit(failures_per_s=1, burst=2))


def _evals(server: RedisServer) -> int:
    return int(server.client().info("commandstats").get("cmdstat_eval", {}).get("calls", 0))


def test_a_tenant_past_its_rate_is_refused_without_asking_redis_again(redis_server: RedisServer) -> None:
    async def flood() -> tuple[list[bool], int]:
        quotas = _quotas(redis_server, rate=2, burst=3)
        answers = [await quotas.take_request(Caller("a", "tag-a")) is None for _ in range(50)]
        return answers, _evals(redis_server)

    answers, evals = asyncio.run(flood())
    assert answers[:3] == [True, True, True] and not any(answers[3:])
    assert evals <= 5, f"{evals} Lua calls for 50 requests: every refusal went to Redis"


def test_the_refusal_ends_when_a_token_is_back_and_other_tenants_are_not_touched(redis_server: RedisServer) -> None:
    async def run() -> None:
        quotas = _quotas(redis_server, rate=10, burst=1)
        assert await quotas.take_request(Caller("a", "tag-a")) is None
        refusal = await quotas.take_request(Caller("a", "tag-a"))
        assert refusal is not None and refusal.limit == "rate" and refusal.retry_after_s >= 1
        assert "'a'" in refusal.message
        assert await quotas.take_request(Caller("b", "tag-b")) is None  # another tenant's bucket is its own
        await asyncio.sleep(0.15)  # one token at 10/s
        assert await quotas.take_request(Caller("a", "tag-a")) is None

    asyncio.run(run())


def test_failed_authentications_block_the_source_for_a_second_at_least(redis_server: RedisServer) -> None:
    async def run() -> None:
        quotas = _quotas(redis_server, rate=100, burst=100)
        assert await quotas.auth_failed("10.0.0.9") is None
        assert await quotas.auth_failed("10.0.0.9") is None
        refusal = await quotas.auth_failed("10.0.0.9")
        assert refusal is not None and refusal.limit == "auth" and refusal.retry_after_s >= 1
        blocked = quotas.auth_blocked("10.0.0.9")
        assert blocked is not None and blocked.limit == "auth"
        assert quotas.auth_blocked("10.0.0.10") is None

    asyncio.run(run())


def test_the_memory_of_who_is_refused_is_bounded() -> None:
    blocked: dict[str, float] = {}
    for i in range(MAX_BLOCKED_SOURCES + 500):
        _remember(blocked, f"s{i}", until=100.0, now=50.0)
    assert len(blocked) == MAX_BLOCKED_SOURCES
    _remember(blocked, "late", until=300.0, now=200.0)  # the others have expired by now: they make room
    assert blocked == {"late": 300.0}
