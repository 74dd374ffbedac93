"""The queue's contract (precond/jobs/queue/) step by step against a redis-server of the test's own: a job is
submitted, taken, finished; another is submitted and cancelled while queued; a third is taken by a worker that then
dies and is handed back by a live worker's beat, taken again, and finished on its second try. Each step is checked
by what the other side reads: the gateway's view of a job (its keys and its stored end), a worker's take."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from redis.asyncio import Redis

from precond.jobs.queue import keys, steps
from precond.jobs.queue.heartbeats import Heartbeat, beat, new_claim
from precond.jobs.queue.keys import (
    ABORTS_KEY,
    CHECK_QUEUE,
    IN_PROGRESS_PREFIX,
    JOB_PREFIX,
    RESULT_PREFIX,
    RUNNING_KEY,
    tenant_jobs_key,
)
from precond.jobs.queue.notices import notice_channel, read_notice
from precond.jobs.queue.payloads import (
    RECORD_VERSION,
    EndRecord,
    Outcome,
    cancelled_end,
    decode_end,
    encode_end,
    encode_job,
)
from precond.stack.local import RedisServer

TAG = "0123456789abcdef"
WAITER = notice_channel("gateway-1")
TAKE = steps.Take(CHECK_QUEUE, "w1", read_limit=4, in_progress_ms=60_000)


def job_id(n: int) -> str:
    return keys.job_id("check", {"n": n}, None, b"secret", TAG)


def claim(worker: str) -> steps.Claim:
    heartbeat = Heartbeat(id=worker, host="h", pid=1, queues=[CHECK_QUEUE], model_loaded=False)
    return steps.Claim(worker, new_claim(worker), heartbeat.model_dump_json(), 60_000)


async def submit(redis: Redis[bytes], job: str, n: int, max_jobs: int = 10, tenant_max_jobs: int = 10) -> bool:
    now = 1_700_000_000_000
    body = encode_job("check", {"n": n}, job, now)
    return await steps.submit(redis, steps.Submission(CHECK_QUEUE, job, TAG, body, now, WAITER), max_jobs,
                              tenant_max_jobs)


async def take(redis: Redis[bytes], by: steps.Claim) -> steps.Taken:
    _, taken, _ = await steps.take(redis, TAKE, 2**45, by, [])
    assert taken is not None
    return taken


async def finish(redis: Redis[bytes], taken: steps.Taken, by: steps.Claim, result: dict[str, Any]) -> int:
    stored = encode_end(EndRecord(version=RECORD_VERSION, job_id=taken.id, queue=CHECK_QUEUE, job_try=taken.job_try,
                                  enqueued_ms=0, start_ms=1, finish_ms=2,
                                  outcome=Outcome(status="succeeded", result=result)))
    return await steps.finish(redis, steps.Finish(CHECK_QUEUE, taken.id, by.token, True, stored, 60_000))


def test_a_job_goes_through_submit_take_finish_cancel_and_hand_back(redis_server: RedisServer) -> None:
    async def scenario(redis: Redis[bytes]) -> None:
        notices = redis.pubsub()
        await notices.subscribe(WAITER)
        first, second, third = job_id(1), job_id(2), job_id(3)

        # submit: queued, counted as the tenant's, and an identical submission shares it
        assert await submit(redis, first, 1)
        assert not await submit(redis, first, 1)
        assert await redis.zscore(tenant_jobs_key(TAG), first) is not None
        with pytest.raises(steps.TenantFull):
            await submit(redis, second, 2, tenant_max_jobs=1)
        with pytest.raises(steps.QueueFull):
            await submit(redis, second, 2, max_jobs=1)

        # take: started (in-progress mark), claimed, its try counted; nothing else to take
        worker = claim("w1")
        taken = await take(redis, worker)
        assert (taken.id, taken.job_try, taken.aborted) == (first, 1, False)
        assert await redis.exists(IN_PROGRESS_PREFIX + first)
        assert await redis.hget(RUNNING_KEY, first) == worker.token.encode()
        assert (await steps.take(redis, TAKE, 2**45, claim("w1"), []))[1] is None

        # finish: stored, its keys and claim gone, its waiter told with the end it carries
        assert await finish(redis, taken, worker, {"verdict": "ok"}) == 0
        end = decode_end(await redis.get(RESULT_PREFIX + first) or b"")
        assert end.outcome is not None and end.outcome.result == {"verdict": "ok"}
        assert not await redis.exists(JOB_PREFIX + first, IN_PROGRESS_PREFIX + first)
        assert not await redis.hexists(RUNNING_KEY, first)
        assert await redis.zscore(tenant_jobs_key(TAG), first) is None  # no longer counted as the tenant's
        noticed = await next_notice(notices)
        assert noticed[0] == first and noticed[2] is not None and decode_end(noticed[2]) == end
        assert not await submit(redis, first, 1)  # its stored end answers an identical request

        # cancel while queued: out of the queue, stored as cancelled, guarded against a take, its waiter told
        assert await submit(redis, second, 2)
        cancelled = cancelled_end(second, CHECK_QUEUE, 5)
        assert await steps.cancel_queued(redis, CHECK_QUEUE, second, cancelled, 60_000)
        assert not await steps.cancel_queued(redis, CHECK_QUEUE, second, cancelled, 60_000)
        assert await redis.zscore(CHECK_QUEUE, second) is None
        assert await redis.zscore(tenant_jobs_key(TAG), second) is None
        failure = decode_end(await redis.get(RESULT_PREFIX + second) or b"").failure
        assert failure is not None and failure.reason == "cancelled"
        assert (await next_notice(notices))[0] == second
        await steps.reopen(redis, second)  # a new request for it runs it again
        assert await submit(redis, second, 2)
        await steps.mark_abort(redis, CHECK_QUEUE, second, 7)
        taken = await take(redis, claim("w1"))
        assert taken.id == second and taken.aborted and not await redis.zscore(ABORTS_KEY, second)

        # hand-back: w2 takes a job and dies (no heartbeat); w1's beat hands it back; it runs again, try 2
        assert await submit(redis, third, 3)
        dead = claim("w2")
        assert (await take(redis, dead)).id == third
        released = await beat(redis, Heartbeat(id="w1", host="h", pid=1, queues=[CHECK_QUEUE], model_loaded=False),
                              5.0)
        assert released == [third] and not await redis.exists(IN_PROGRESS_PREFIX + third)
        live = claim("w1")
        retaken = await take(redis, live)
        assert (retaken.id, retaken.job_try) == (third, 2)
        await finish(redis, retaken, live, {"verdict": "ok"})
        end = decode_end(await redis.get(RESULT_PREFIX + third) or b"")
        assert end.outcome is not None and end.job_try == 2
        await notices.aclose()  # type: ignore[attr-defined]

    redis_server.run(scenario)


def test_a_tenant_at_its_cap_is_refused_until_its_vanished_jobs_leave_its_count(redis_server: RedisServer) -> None:
    """A job whose bytes vanished without an end (expired) still counts until the tenant looks full; then the
    submit drops it from the count, and an identical request for a job the tenant has is never refused."""
    async def scenario(redis: Redis[bytes]) -> None:
        first, second, third = job_id(1), job_id(2), job_id(3)
        assert await submit(redis, first, 1, tenant_max_jobs=2)
        assert await submit(redis, second, 2, tenant_max_jobs=2)
        assert not await submit(redis, second, 2, tenant_max_jobs=2)
        with pytest.raises(steps.TenantFull) as full:
            await submit(redis, third, 3, tenant_max_jobs=2)
        assert full.value.count == 2
        await redis.delete(JOB_PREFIX + first)
        assert await submit(redis, third, 3, tenant_max_jobs=2)
        assert await redis.zscore(tenant_jobs_key(TAG), first) is None

    redis_server.run(scenario)


async def next_notice(notices: Any) -> tuple[str, bytes | None, bytes | None]:
    deadline = asyncio.get_running_loop().time() + 5
    while asyncio.get_running_loop().time() < deadline:
        message = await notices.get_message(ignore_subscribe_messages=True, timeout=1)
        if message is not None:
            return read_notice(message["data"])
    raise AssertionError("no notice")


def test_the_take_skips_a_tenant_by_its_tag_whatever_the_kind(redis_server: RedisServer) -> None:
    """The take reads a job's tenant as `JobId` does (the part between the id's last two dashes), also for kinds
    whose names have dashes of their own."""
    busy, other = "aaaaaaaaaaaaaaaa", "bbbbbbbbbbbbbbbb"

    async def scenario(redis: Redis[bytes]) -> None:
        ids = [keys.job_id(kind, {}, None, b"secret", tag) for kind, tag in
               (("next-action", busy), ("train-policy", busy), ("check", other))]
        for score, job in enumerate(ids, start=1):
            await redis.zadd(CHECK_QUEUE, {job: score})
            await redis.set(JOB_PREFIX + job, encode_job("check", {}, job, 0))
        _, taken, _ = await steps.take(redis, TAKE, 2**45, claim("w1"), [busy])
        assert taken is not None and taken.id == ids[2]
        assert keys.JobId.parse(ids[0]).tenant == busy

    redis_server.run(scenario)
