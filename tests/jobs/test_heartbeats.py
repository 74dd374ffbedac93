"""Crash recovery's one Lua script (`precond.jobs.queue.heartbeats._BEAT`) against a real redis-server: whose jobs
a beat hands back to the queue, and whose it never touches."""

from __future__ import annotations

import asyncio
import time

from arq.constants import in_progress_key_prefix, result_key_prefix
from redis.asyncio import Redis

from precond.jobs.queue.heartbeats import Heartbeat, beat, live_workers, new_claim
from precond.jobs.queue.keys import CHECK_QUEUE, RUNNING_KEY, STATS_KEY, UNCLAIMED_KEY, worker_key
from precond.stack.local import RedisServer

TTL_S = 0.5


def heartbeat(worker: str) -> Heartbeat:
    return Heartbeat(id=worker, host="h", pid=1, queues=[CHECK_QUEUE], model_loaded=False)


async def started(redis: Redis[bytes], job: str) -> None:
    """A job as arq leaves it once a worker took it: still in its queue, with an in-progress key."""
    await redis.zadd(CHECK_QUEUE, {job: time.time() * 1000})
    await redis.set(in_progress_key_prefix + job, b"1")


async def claim(redis: Redis[bytes], worker: Heartbeat, ttl_s: float, job: str, token: str) -> None:
    """A claim as the worker's take writes it (precond.worker.queue_worker): the job's claim under a fresh heartbeat."""
    await redis.set(worker_key(worker.id), worker.model_dump_json(), px=int(ttl_s * 1000))
    await redis.hset(RUNNING_KEY, job, token)



def test_a_dead_workers_unfinished_job_goes_back_and_a_live_workers_stays(redis_server: RedisServer) -> None:
    async def scenario(redis: Redis[bytes]) -> None:
        for job in ("dead-job", "live-job", "dead-but-done"):
            await started(redis, job)
        await claim(redis, heartbeat("dead"), TTL_S, "dead-job", new_claim("dead"))
        await claim(redis, heartbeat("dead"), TTL_S, "dead-but-done", new_claim("dead"))
        await redis.set(result_key_prefix + "dead-but-done", b"r")
        await claim(redis, heartbeat("live"), 60, "live-job", new_claim("live"))
        await asyncio.sleep(TTL_S + 0.2)  # the dead worker's heartbeat lapses; the live one's does not
        assert [w.id for w in await live_workers(redis)] == ["live"]

        released = await beat(redis, heartbeat("other"), 60)

        assert released == ["dead-job"]
        assert not await redis.exists(in_progress_key_prefix + "dead-job")  # any worker's next poll runs it
        assert await redis.exists(in_progress_key_prefix + "live-job")
        assert set(await redis.hkeys(RUNNING_KEY)) == {b"live-job"}  # the finished job's claim is dropped too

    redis_server.run(scenario)


def test_a_beat_adds_the_counts_its_worker_added_up_and_keeps_its_claims(redis_server: RedisServer) -> None:
    """The stats of the runs a worker ended since its last beat go with the beat, beside its running claims."""
    async def scenario(redis: Redis[bytes]) -> None:
        await redis.hset(STATS_KEY, "jobs:check:succeeded", 2)
        await started(redis, "running")
        token = new_claim("w1")
        counts = {"jobs:check:succeeded": 3.0, "queue_sum:t:check": 0.25}
        assert await beat(redis, heartbeat("w1"), 60, running={"running": token}, counts=counts) == []
        stats = await redis.hgetall(STATS_KEY)
        assert float(stats[b"jobs:check:succeeded"]) == 5.0 and float(stats[b"queue_sum:t:check"]) == 0.25
        assert await redis.hget(RUNNING_KEY, "running") == token.encode()
        await beat(redis, heartbeat("w1"), 60)  # nothing added up: nothing added
        assert float(await redis.hget(STATS_KEY, "jobs:check:succeeded") or 0) == 5.0

    redis_server.run(scenario)


def test_runs_a_worker_dropped_go_back_at_once_and_lost_claims_are_written_again(redis_server: RedisServer) -> None:
    """Redis went away mid-job (arq could not record the end: dropped), or came back without the claims."""
    async def scenario(redis: Redis[bytes]) -> None:
        await started(redis, "dropped")
        await started(redis, "running")
        token = new_claim("w")
        await claim(redis, heartbeat("w"), 60, "dropped", token)
        running = new_claim("w")

        released = await beat(redis, heartbeat("w"), 60, running={"running": running}, dropped={token})

        assert released == ["dropped"]
        assert not await redis.exists(in_progress_key_prefix + "dropped")
        assert await redis.hget(RUNNING_KEY, "running") == running.encode()
        assert await redis.exists(worker_key("w"))

    redis_server.run(scenario)


def test_a_job_started_and_never_claimed_goes_back_a_lease_later(redis_server: RedisServer) -> None:
    """A worker SIGKILLed between arq's start and its claim: noted by one beat, handed back a lease later."""
    async def scenario(redis: Redis[bytes]) -> None:
        await started(redis, "orphan")
        assert await beat(redis, heartbeat("w"), TTL_S) == []
        assert await redis.hexists(UNCLAIMED_KEY, "orphan")
        await asyncio.sleep(TTL_S + 0.1)
        assert await beat(redis, heartbeat("w"), TTL_S) == ["orphan"]
        assert not await redis.exists(in_progress_key_prefix + "orphan")
        assert not await redis.hexists(UNCLAIMED_KEY, "orphan")

    redis_server.run(scenario)
