"""Per-tenant limits and fair ordering, kept in Redis so that every gateway sees the same counts.

- A token bucket per tenant bounds its request rate on every route (`PRECOND_TENANT_RATE_PER_S`,
  `PRECOND_TENANT_BURST`), and one per source address its failed authentications
  (`PRECOND_AUTH_FAILURES_PER_S`, `PRECOND_AUTH_FAILURE_BURST`): a source whose bucket is empty gets 429
  before its key is even looked at, on every gateway process that saw it fail.
- A set per tenant of its unfinished jobs bounds how many it may have queued or running
  (`PRECOND_TENANT_MAX_JOBS`); a job leaves the set once arq's job key is gone (done, failed or cancelled).
- Fair ordering: arq serves a queue in score order, and a job's score here is its tenant's *virtual start
  time*, not its arrival time: one more than the larger of the queue's head and the tenant's last job. A
  tenant with 500 jobs queued has scores far ahead; another tenant's one job lands right behind the head,
  so it waits for at most the jobs already running plus one. Scores count up from a fixed epoch long past,
  so every job is due at once (arq treats a score as the time a job may start).

Each rule is Lua run by Redis atomically, so concurrent requests cannot both take the last slot; the job cap
and the fair place are functions of the queue's one submission script (`precond.jobs.queue.steps`), which admits,
places and enqueues a job in one step.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Final

from redis.asyncio import Redis
from redis.exceptions import OutOfMemoryError  # type: ignore[attr-defined]  # types-redis predates it

from precond.gateway.caller import Caller
from precond.jobs.queue.keys import PREFIX
from precond.jobs.scripts import LuaScript

_TAKE_TOKENS = LuaScript("""
local rate, burst, want = tonumber(ARGV[1]), tonumber(ARGV[2]), tonumber(ARGV[3])
local clock = redis.call('TIME')
local now = tonumber(clock[1]) + tonumber(clock[2]) / 1e6
local state = redis.call('HMGET', KEYS[1], 'tokens', 'at')
local tokens, at = tonumber(state[1]) or burst, tonumber(state[2]) or now
now = math.max(now, at)
tokens = math.min(burst, tokens + (now - at) * rate)
local granted = math.min(want, math.floor(tokens))
tokens = tokens - granted
redis.call('HSET', KEYS[1], 'tokens', tostring(tokens), 'at', tostring(now))
redis.call('EXPIRE', KEYS[1], math.ceil(burst / rate) + 60)
return {granted, tostring(tokens)}
""")
"""Up to `want` whole tokens from a bucket: how many it gave, and what is left (a fraction below one when none).
The bucket's clock is Redis's own (`TIME`), and never goes back: every gateway process shares one bucket, and a
clock read by each process before its round trip let a slow or skewed one stamp the bucket with an earlier time,
so that the next refill counted the same seconds twice (bursts past `burst + rate × time`)."""

LEASE_S: Final = 0.25
"""How long a gateway process may spend the tokens it took ahead of its requests (`Lease`)."""
MAX_LEASE: Final = 64

@dataclass(frozen=True)
class Refusal:
    """Which limit a request hit, for its 429."""

    limit: str  # "rate" | "jobs" | "auth"
    message: str
    retry_after_s: int


def _rate_key(tag: str) -> str:
    return f"{PREFIX}:tenant:{tag}:rate"


def _auth_key(source: str) -> str:
    return f"{PREFIX}:source:{source}:auth-failures"


@dataclass(frozen=True)
class AuthLimit:
    failures_per_s: float
    burst: int


MAX_BLOCKED_SOURCES: Final = 10_000


@dataclass
class Lease:
    """Tokens a gateway process took from a tenant's bucket ahead of its requests, spent here without Redis.

    A busy tenant's every request took its token in a round trip to Redis: a fifth of the gateway's CPU per
    cache hit. A lease takes several at once; every token spent was taken from the shared bucket first, so
    across processes a tenant still never gets more than its rate and burst allow. A token left when the lease
    ends (`LEASE_S`) is lost: the tenant gets less, never more. A lease's size follows the tenant's demand in
    this process: one token at first (a tenant whose requests come more than `LEASE_S` apart takes one token a
    request, as before), twice the last when that was spent within its time, what was spent of it when not,
    and never more than a quarter of the burst or what the rate refills in `LEASE_S` (so that the other
    processes of a tenant near its limit are not refused while this one holds its tokens)."""

    size: int
    tokens: int
    until: float

    def next_size(self, now: float, largest: int) -> int:
        spent = self.size - self.tokens
        return min(largest, 2 * self.size if self.tokens == 0 and now <= self.until else max(1, spent))


class SourceBuckets:
    """Token buckets per source address kept in this process, for the routes open without a key (`/health`,
    `/ready`, `/metrics`): they must answer while Redis is down, so their rate cannot live there."""

    def __init__(self, rate_per_s: float, burst: int) -> None:
        self.rate_per_s, self.burst = rate_per_s, burst
        self._buckets: dict[str, tuple[float, float]] = {}  # source -> (tokens, at)

    def take(self, source: str) -> Refusal | None:
        now = datetime.now(UTC).timestamp()
        if len(self._buckets) >= MAX_BLOCKED_SOURCES:  # keep only the empty ones (a forgotten bucket is full)
            self._buckets = {s: b for s, b in self._buckets.items() if b[0] + (now - b[1]) * self.rate_per_s < 1}
        tokens, at = self._buckets.get(source, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - at) * self.rate_per_s)
        if tokens < 1:
            self._buckets[source] = (tokens, now)
            wait = max(1, math.ceil((1 - tokens) / self.rate_per_s))
            return Refusal("rate", f"rate limit: this address may call the open routes {self.rate_per_s:g} "
                                   f"times/s (bursts of {self.burst})", wait)
        self._buckets[source] = (tokens - 1, now)
        return None


def _remember(blocked: dict[str, float], who: str, until: float, now: float) -> None:
    """Note until when `who` is refused, keeping at most MAX_BLOCKED_SOURCES live entries."""
    if len(blocked) >= MAX_BLOCKED_SOURCES:
        for stale in [k for k, t in blocked.items() if t <= now]:
            del blocked[stale]
        if len(blocked) >= MAX_BLOCKED_SOURCES:
            return  # all live: this one is asked of Redis each time, as before
    blocked[who] = until


class Quotas:
    def __init__(self, redis: Redis[bytes], rate_per_s: float, burst: int, max_jobs: int, auth: AuthLimit) -> None:
        self.redis, self.rate_per_s, self.burst, self.max_jobs, self.auth = redis, rate_per_s, burst, max_jobs, auth
        self._blocked: dict[str, float] = {}  # source -> until (this process's view of the shared buckets)
        self._empty: dict[str, float] = {}  # tenant tag -> until its rate bucket has a token again
        self._leases: dict[str, Lease] = {}  # tenant tag -> its tokens taken ahead (bounded as `_remember` is)
        self._leasing: dict[str, asyncio.Future[None]] = {}  # tenant tag -> its lease being taken now
        self._largest_lease = max(1, min(MAX_LEASE, burst // 4, math.floor(rate_per_s * LEASE_S)))

    async def _take(self, key: str, rate: float, burst: int, want: int = 1) -> tuple[int, float]:
        """Up to `want` tokens from the bucket at `key`: how many, and the seconds until the next one when none.
        While the queue Redis is full (noeviction refuses the bucket's write) the request goes on uncounted:
        reading a job's state must keep working then, and every request that would write is refused by that
        Redis anyway."""
        try:
            granted, tokens = await _TAKE_TOKENS(self.redis, [key], [rate, burst, want])
        except OutOfMemoryError:
            return 1, 0.0
        return int(granted), max(0.0, (1 - float(tokens)) / rate)

    async def take_request(self, caller: Caller) -> Refusal | None:
        """A token of the tenant's rate: from this process's lease when it holds one (`Lease`), else from the
        shared bucket. While this process knows the bucket is empty, the refusal costs no Redis round trip: a
        tenant flooding past its rate must not cost the others the shared Redis's time."""
        now = datetime.now(UTC).timestamp()
        while True:
            lease = self._leases.get(caller.tag)
            if lease is not None and lease.tokens > 0 and now <= lease.until:
                lease.tokens -= 1
                return None
            until = self._empty.get(caller.tag, 0.0)
            if until > now:
                return self._rate_refusal(caller, until - now)
            on_its_way = self._leasing.get(caller.tag)
            if on_its_way is None:
                granted, wait = await self._take_for(caller.tag, lease, now)
                break
            if self._largest_lease == 1:  # a lease is the one token of the request that took it: none to share
                granted, wait = await self._take(_rate_key(caller.tag), self.rate_per_s, self.burst)
                break
            # then spend the lease it brought, or take the next one (shielded: a waiter cancelled, its client
            # gone, must not cancel what the others wait for)
            await asyncio.shield(on_its_way)
            now = datetime.now(UTC).timestamp()
        if granted:
            return None
        _remember(self._empty, caller.tag, now + wait, now)
        return self._rate_refusal(caller, wait)

    def _rate_refusal(self, caller: Caller, wait: float) -> Refusal:
        return Refusal("rate", f"rate limit: tenant {caller.name!r} may send {self.rate_per_s:g} requests/s "
                               f"(bursts of {self.burst})", max(1, math.ceil(wait)))

    async def _take_for(self, tag: str, lease: Lease | None, now: float) -> tuple[int, float]:
        """Tokens for a request that found no lease to spend, taken as the tenant's next lease (its grant
        replaces the spent or ended lease). One take at a time per tenant: the requests that come while it is
        on the way wait for it (`take_request`; where a lease may hold more than one token) and spend its
        tokens, so that concurrent requests neither hoard the bucket nor overwrite each other's leases (whose
        tokens, taken from the bucket, would then be lost), nor each take a token of their own in a round trip
        to Redis (32 connections of one tenant made most requests such a round trip whenever a lease ran out)."""
        on_its_way: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._leasing[tag] = on_its_way
        try:
            want = 1 if lease is None else lease.next_size(now, self._largest_lease)
            granted, wait = await self._take(_rate_key(tag), self.rate_per_s, self.burst, want)
            if granted:
                self._lease(tag, Lease(granted, granted - 1, now + LEASE_S), now)
        finally:
            del self._leasing[tag]
            on_its_way.set_result(None)
        return granted, wait

    def auth_blocked(self, source: str) -> Refusal | None:
        """Whether this source used up its failed authentications (no Redis: checked before every key)."""
        until = self._blocked.get(source)
        now = datetime.now(UTC).timestamp()
        if until is None or until <= now:
            return None
        return self._auth_refusal(math.ceil(until - now))

    def _lease(self, tag: str, lease: Lease, now: float) -> None:
        """Keep `lease`, within MAX_BLOCKED_SOURCES leases (the page's sources count as tenants here): the
        ended ones make room, and with none ended the new one is not kept (its tokens are lost)."""
        if tag not in self._leases and len(self._leases) >= MAX_BLOCKED_SOURCES:
            self._leases = {t: kept for t, kept in self._leases.items() if kept.until >= now}
            if len(self._leases) >= MAX_BLOCKED_SOURCES:
                return
        self._leases[tag] = lease

    async def auth_failed(self, source: str) -> Refusal | None:
        """Count one failed authentication of `source`; a refusal once its bucket is empty."""
        granted, taken = await self._take(_auth_key(source), self.auth.failures_per_s, self.auth.burst)
        if granted:
            return None
        wait = max(1, math.ceil(taken))  # a whole second at least: a penalty, not just the next token
        now = datetime.now(UTC).timestamp()
        _remember(self._blocked, source, now + wait, now)
        return self._auth_refusal(wait)

    def _auth_refusal(self, wait: int) -> Refusal:
        return Refusal("auth", f"too many failed authentications from this address: at most "
                               f"{self.auth.failures_per_s:g}/s (bursts of {self.auth.burst})", max(1, wait))

    def jobs_refusal(self, caller: Caller, count: int, retry_after_s: int) -> Refusal:
        """The 429 of a tenant at its cap of queued and running jobs (`PRECOND_TENANT_MAX_JOBS`)."""
        return Refusal("jobs", f"job limit: tenant {caller.name!r} has {count} jobs queued or running "
                               f"(at most {self.max_jobs})", retry_after_s)
