"""The gateway's per-tenant and per-source limits against a real redis-server: what a flood costs the shared
Redis, and that the limits let a tenant through again once its bucket has a token."""

from __future__ import annotations

import asyncio
import time
from datetime import datetime, tzinfo

import pytest
from redis.asyncio import ConnectionPool, Redis

from precond.gateway import quotas as quotas_module
from precond.gateway.caller import Caller
from precond.gateway.quotas import LEASE_S, MAX_BLOCKED_SOURCES, AuthLimit, Lease, Quotas, _remember
from precond.stack.local import RedisServer


def _quotas(server: RedisServer, rate: float, burst: int) -> Quotas:
    redis: Redis[bytes] = Redis(connection_pool=ConnectionPool.from_url(server.url))
    return Quotas(redis, rate, burst, max_jobs=4, auth=AuthLimit(failures_per_s=1, burst=2))


def _lua_calls(server: RedisServer) -> int:
    """Lua calls so far: by its text (EVAL) or, once Redis has it, by its digest (EVALSHA, `LuaScript`)."""
    stats = server.client().info("commandstats")
    return sum(int(stats.get(f"cmdstat_{name}", {}).get("calls", 0)) for name in ("eval", "evalsha"))


def test_a_tenant_past_its_rate_is_refused_without_asking_redis_again(redis_server: RedisServer) -> None:
    async def flood() -> tuple[list[bool], int]:
        quotas = _quotas(redis_server, rate=2, burst=3)
        answers = [await quotas.take_request(Caller("a", "tag-a")) is None for _ in range(50)]
        return answers, _lua_calls(redis_server)

    answers, evals = asyncio.run(flood())
    assert answers[:3] == [True, True, True] and not any(answers[3:])
    assert evals <= 5, f"{evals} Lua calls for 50 requests: every refusal went to Redis"


def test_busy_processes_take_tokens_in_leases_and_never_more_than_the_bucket_gives(
    redis_server: RedisServer,
) -> None:
    """Two gateway processes of one tenant, each sending as fast as it can for half a second: together they are
    let through no more than the burst and what the rate refilled, and the requests cost few round trips to Redis:
    the burst is taken in leases, and a refused request waits for the next token without asking again. At the
    limit each token the rate refills costs a round trip (a lease holds what the bucket has, one token), so the
    Lua calls are bounded by the tokens granted and the refusals' windows, not by the requests made."""
    rate, burst = 400.0, 100

    async def flood() -> tuple[int, int, float, int]:
        processes = [_quotas(redis_server, rate=rate, burst=burst) for _ in range(2)]
        allowed, made, caller = 0, 0, Caller("a", "tag-a")
        before = _lua_calls(redis_server)
        started = time.monotonic()
        while time.monotonic() - started < 0.5:
            for quotas in processes:
                allowed += await quotas.take_request(caller) is None
                made += 1
        return allowed, made, time.monotonic() - started, _lua_calls(redis_server) - before

    allowed, made, elapsed, calls = asyncio.run(flood())
    assert allowed <= burst + rate * (elapsed + 0.05), f"{allowed} let through in {elapsed:.2f} s"
    assert allowed >= 0.5 * (burst + rate * elapsed), f"only {allowed} let through in {elapsed:.2f} s"
    assert calls <= made / 10, f"{calls} Lua calls for {made} requests"
    assert calls <= allowed + 2 * rate * (elapsed + 0.05), f"{calls} Lua calls for {allowed} requests let through"


class SkewedClock:
    """The clock each gateway process reads: `offset` seconds off the real one (set before each call)."""

    offset = 0.0

    @classmethod
    def now(cls, tz: tzinfo | None = None) -> datetime:
        return datetime.fromtimestamp(time.time() + cls.offset, tz)


def test_gateway_processes_with_skewed_clocks_get_no_more_than_the_bucket_gives(
    redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two gateway processes whose clocks are 30 s apart (or one that read its clock long before its round trip
    to Redis) take tokens from one bucket in turn: a bucket stamped with each process's own time went back and
    forth, and each step forward refilled it again. Together they still get at most burst + rate × time."""
    rate, burst = 1.0, 5
    monkeypatch.setattr(quotas_module, "datetime", SkewedClock)

    async def alternate() -> tuple[int, float]:
        processes = [_quotas(redis_server, rate=rate, burst=burst) for _ in range(2)]
        granted, started = 0, time.monotonic()
        for turn in range(40):
            SkewedClock.offset = -30.0 * (turn % 2)
            granted += (await processes[turn % 2]._take("precond:tenant:skew:rate", rate, burst))[0]
        return granted, time.monotonic() - started

    granted, elapsed = asyncio.run(alternate())
    assert granted <= burst + rate * elapsed + 1, f"{granted} tokens given in {elapsed:.2f} s"


def test_concurrent_requests_of_a_tenant_lose_no_token_they_took(redis_server: RedisServer) -> None:
    """Sixteen requests at a time: every token taken from the bucket is spent or still in the live lease (a
    lease overwritten by a concurrent one lost its tokens: the tenant was refused under its rate)."""

    async def run() -> tuple[int, int, int]:
        quotas = _quotas(redis_server, rate=400, burst=100)
        taken, take = [0], quotas._take

        async def counted(key: str, rate: float, burst: int, want: int = 1) -> tuple[int, float]:
            granted, wait = await take(key, rate, burst, want)
            taken[0] += granted
            return granted, wait

        quotas._take = counted  # type: ignore[method-assign]
        allowed = 0
        for _ in range(20):
            answers = await asyncio.gather(*(quotas.take_request(Caller("a", "tag-a")) for _ in range(16)))
            allowed += sum(answer is None for answer in answers)
        lease = quotas._leases.get("tag-a")
        return taken[0], allowed, lease.tokens if lease is not None else 0

    taken, allowed, left = asyncio.run(run())
    assert taken == allowed + left, f"{taken} tokens taken, {allowed} requests let through, {left} left"


def test_concurrent_requests_spend_the_lease_on_its_way_rather_than_ask_redis(redis_server: RedisServer) -> None:
    """Thirty-two requests of a busy tenant at a time (a gateway process under load): those that come while
    its lease is being taken wait for it and spend its tokens; each one asking Redis for a token of its own
    cost the gateway a round trip per request."""

    async def run() -> tuple[int, int]:
        quotas = _quotas(redis_server, rate=100_000, burst=100_000)
        allowed = 0
        for _ in range(20):
            answers = await asyncio.gather(*(quotas.take_request(Caller("a", "tag-a")) for _ in range(32)))
            allowed += sum(answer is None for answer in answers)
        return allowed, _lua_calls(redis_server)

    allowed, evals = asyncio.run(run())
    assert allowed == 640
    assert evals <= 640 / 16, f"{evals} Lua calls for {allowed} requests"


def test_a_request_cancelled_while_waiting_for_the_lease_cancels_no_other(redis_server: RedisServer) -> None:
    """A client gone while its request waited for the tenant's lease on its way: the lease is still taken and
    the other requests waiting for it are let through."""

    async def run() -> list[object]:
        quotas = _quotas(redis_server, rate=100_000, burst=100_000)
        tasks = [asyncio.create_task(quotas.take_request(Caller("a", "tag-a"))) for _ in range(8)]
        await asyncio.sleep(0)  # every one started: the first takes the lease, the others wait for it
        tasks[1].cancel()
        return await asyncio.gather(*tasks, return_exceptions=True)

    answers = asyncio.run(run())
    assert isinstance(answers[1], asyncio.CancelledError)
    assert [answer for i, answer in enumerate(answers) if i != 1] == [None] * 7, answers


def test_a_tenant_of_a_low_rate_takes_one_token_a_request(redis_server: RedisServer) -> None:
    async def run() -> tuple[int, float]:
        quotas = _quotas(redis_server, rate=20, burst=100)  # 20/s refills 5 tokens in a lease's time: no more
        for _ in range(10):
            assert await quotas.take_request(Caller("a", "tag-a")) is None
        tokens = await quotas.redis.hget("precond:tenant:tag-a:rate", "tokens")
        return _lua_calls(redis_server), float(tokens or 0)

    evals, tokens = asyncio.run(run())
    assert evals < 10  # leases of 1, 2, 4 and then at most 5 tokens
    assert tokens <= 100 - 10 + 1  # every token spent came from the bucket (plus what refilled meanwhile)


def test_a_lease_grows_while_it_is_spent_in_time_and_shrinks_to_what_was_spent() -> None:
    assert Lease(size=4, tokens=0, until=10.0).next_size(now=9.0, largest=64) == 8
    assert Lease(size=4, tokens=0, until=10.0).next_size(now=9.0, largest=6) == 6
    assert Lease(size=8, tokens=5, until=10.0).next_size(now=11.0, largest=64) == 3
    assert Lease(size=8, tokens=8, until=10.0).next_size(now=11.0, largest=64) == 1
    assert Lease(size=8, tokens=0, until=10.0).next_size(now=11.0, largest=64) == 8


def test_the_memory_of_leases_is_bounded(redis_server: RedisServer) -> None:
    quotas = _quotas(redis_server, rate=1000, burst=1000)
    for i in range(MAX_BLOCKED_SOURCES + 500):
        quotas._lease(f"t{i}", Lease(4, 3, until=100.0), now=50.0)
    assert len(quotas._leases) == MAX_BLOCKED_SOURCES
    quotas._lease("late", Lease(4, 3, until=100.0 + LEASE_S), now=200.0)  # the others ended: they make room
    assert list(quotas._leases) == ["late"]


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
