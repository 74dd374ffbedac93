"""The queue worker's loop (precond/worker/queue_worker.py) against a real redis-server: a job is claimed with its
in-progress key in one step, ends with its stored end, the claim's release and the notice in one step (its counts
kept for the worker's next heartbeat), and every way a run ends (expired, aborted before it started, out of tries,
timed out, cancelled by a shutdown) ends as its stored end record says."""

from __future__ import annotations

import asyncio
import contextlib
import json
import pickle
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import pytest
from arq.constants import abort_jobs_ss, in_progress_key_prefix, job_key_prefix, result_key_prefix, retry_key_prefix
from redis.asyncio import Redis
from redis.exceptions import RedisError

from precond.jobs.queue import keys, steps
from precond.jobs.queue.heartbeats import Heartbeat, beat
from precond.jobs.queue.keys import RUNNING_KEY, wake_channel, worker_key
from precond.jobs.queue.notices import notice_channel, read_notice, waiters_key
from precond.jobs.queue.payloads import EndRecord, Outcome, decode_end, encode_job
from precond.jobs.records import PendingCounts
from precond.stack.local import RedisServer
from precond.worker import queue_worker
from precond.worker.queue_worker import JobContext, JobEnd, QueueWorker, RunSettings
from precond.worker.runner import RunClaims

QUEUE = "test:queue"
TAG = "0123456789abcdef"


def job_id(n: int, tag: str = TAG) -> str:
    return keys.job_id("check", {"n": n}, None, b"secret", tag)


def heartbeat() -> Heartbeat:
    return Heartbeat(id="w1", host="h", pid=1, queues=[QUEUE], model_loaded=False)


Operation = Callable[[dict[str, Any], int], Coroutine[Any, Any, JobEnd]]
"""A test's job function: the worker's, given the `n` of the job's body."""


def done(n: int) -> Outcome:
    return Outcome(status="succeeded", result={"n": n})


async def answer(ctx: JobContext, n: int) -> JobEnd:
    return JobEnd(done(n), {"jobs:test:succeeded": 1.0})


async def enqueue(plain: Redis[bytes], job: str, n: int) -> None:
    """A check job whose body is `{"n": n}`, queued as the gateway's submission queues it (due at once)."""
    await plain.set(job_key_prefix + job, encode_job("check", {"n": n}, job, 1), px=60_000)
    await plain.zadd(QUEUE, {job: 1})


def long_run(started: asyncio.Event) -> Operation:
    """An operation that says it started, then runs for half a minute (until a shutdown, an abort or a timeout)."""
    async def operation(ctx: JobContext, n: int) -> JobEnd:
        started.set()
        await asyncio.sleep(30)
        return JobEnd(done(n))

    return operation


def run(redis_server: RedisServer, scenario: Callable[[Redis[bytes]], Awaitable[None]]) -> None:
    async def main() -> None:
        plain: Redis[bytes] = Redis.from_url(redis_server.url)
        try:
            await scenario(plain)
        finally:
            await plain.aclose()  # type: ignore[attr-defined]

    asyncio.run(main())


@contextlib.asynccontextmanager
async def worker(redis_server: RedisServer, operation: Operation = answer, timeout_s: float = 30,
                 max_tries: int = 3, claims: RunClaims | None = None, idle_poll_s: float = 0.05) -> Any:
    claims = claims or RunClaims("w1", heartbeat, 5.0)
    settings = RunSettings(QUEUE, max_jobs=2, tenant_slots=2, timeout_s=timeout_s, keep_result_s=60,
                           max_tries=max_tries, idle_poll_s=idle_poll_s)
    queue_worker = QueueWorker(lambda ctx, kind, body, cache_key: operation(ctx, body["n"]), settings,
                               redis_server.url, claims, PendingCounts())
    task = asyncio.create_task(queue_worker.run())
    try:
        yield queue_worker
    finally:
        queue_worker.stop()
        # a Redis error ends the run, and its close (the worker process starts another: precond/worker/runner.py)
        with contextlib.suppress(RedisError):
            await task
        with contextlib.suppress(RedisError):
            await queue_worker.close()


async def result_of(plain: Redis[bytes], job: str, timeout_s: float = 10) -> EndRecord:
    """The job's stored end, once there is one."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while (raw := await plain.get(result_key_prefix + job)) is None:
        assert asyncio.get_running_loop().time() < deadline, f"{job} never ended"
        await asyncio.sleep(0.02)
    return decode_end(raw)


def test_a_run_is_claimed_with_its_start_and_ends_in_one_step(redis_server: RedisServer) -> None:
    seen: dict[str, Any] = {}

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:  # what holds while the job runs
            seen["claim"] = await plain.hget(RUNNING_KEY, ctx.job.value)
            seen["heartbeat"] = await plain.get(worker_key("w1"))
            seen["in_progress"] = await plain.exists(in_progress_key_prefix + ctx.job.value)
            return JobEnd(done(n), {"jobs:test:succeeded": 1.0})

        job = job_id(1)
        notices = plain.pubsub()
        await notices.subscribe(notice_channel("gateway-1"))
        await enqueue(plain, job, 7)
        await plain.sadd(waiters_key(job), notice_channel("gateway-1"))  # as the gateway's submission does
        async with worker(redis_server, operation) as running:
            info = await result_of(plain, job)
        assert info.outcome == done(7) and info.job_try == 1
        assert seen["claim"].decode().startswith("w1|") and seen["in_progress"] == 1
        beat_written = Heartbeat.model_validate_json(seen["heartbeat"])
        assert beat_written.id == "w1" and beat_written.jobs_started == 1  # the run it claims counted already
        for key in (in_progress_key_prefix, job_key_prefix, retry_key_prefix):
            assert not await plain.exists(key + job)
        assert await plain.zscore(QUEUE, job) is None
        assert not await plain.hexists(RUNNING_KEY, job)  # the claim went with the end
        stats = running.stats.take()  # added up for the process's next heartbeat
        assert stats["jobs:test:succeeded"] == 1.0 and stats[f"queue_count:{TAG}:check"] == 1.0
        messages = [await notices.get_message(timeout=1) for _ in range(2)]  # the subscription's, then the notice
        assert [m["type"] for m in messages if m] == ["subscribe", "message"], messages
        noticed, progress, end = read_notice(messages[1]["data"])  # the end as stored, carried
        assert noticed == job and progress == b"" and end is not None
        assert decode_end(end) == info
        assert not await plain.exists(waiters_key(job))  # told once, then forgotten
        await notices.aclose()  # type: ignore[attr-defined]

    run(redis_server, scenario)


def test_a_finish_releases_its_own_runs_claim_only(redis_server: RedisServer) -> None:
    """A later run of the same job (another worker took it after this one's claim was handed back) keeps its
    claim when the earlier run's end is recorded."""
    claims = RunClaims("w1", heartbeat, 5.0)

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            await plain.hset(RUNNING_KEY, ctx.job.value, "w2|later")
            return JobEnd(done(n))

        job = job_id(2)
        await enqueue(plain, job, 1)
        async with worker(redis_server, operation, claims=claims):
            await result_of(plain, job)
        assert await plain.hget(RUNNING_KEY, job) == b"w2|later"
        assert claims.live == {} and claims.dropped == set()

    run(redis_server, scenario)


@pytest.mark.parametrize("progressed", [True, False])
def test_a_notice_carries_the_progress_of_a_run_that_wrote_some(redis_server: RedisServer, progressed: bool) -> None:
    """The end's notice carries the job's last progress as stored; a run that wrote none has its end spare the
    read, and its notice carries none."""
    stored = b'{"version":1,"phase":"judge","done":2,"total":3}'

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            await plain.set(keys.progress_key(ctx.job.value), stored)
            return JobEnd(done(n), progressed=progressed)

        job = job_id(4)
        notices = plain.pubsub()
        await notices.subscribe(notice_channel("gateway-1"))
        await enqueue(plain, job, 1)
        await plain.sadd(waiters_key(job), notice_channel("gateway-1"))
        async with worker(redis_server, operation):
            await result_of(plain, job)
        messages = [await notices.get_message(timeout=1) for _ in range(2)]
        assert messages[1] is not None, messages
        noticed, progress, end = read_notice(messages[1]["data"])
        assert noticed == job and end is not None and progress == (stored if progressed else b"")
        await notices.aclose()  # type: ignore[attr-defined]

    run(redis_server, scenario)


@pytest.mark.parametrize("how", ["expired", "aborted", "out of tries"])
def test_a_job_that_must_not_run_ends_failed_with_the_reason(redis_server: RedisServer, how: str) -> None:
    ran: list[int] = []

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            ran.append(n)
            return JobEnd(done(n))

        job = job_id(3)
        await enqueue(plain, job, 1)
        if how == "expired":
            await plain.delete(job_key_prefix + job)
        elif how == "aborted":
            await plain.zadd(abort_jobs_ss, {job: 1})
        else:
            await plain.set(retry_key_prefix + job, 3)
        async with worker(redis_server, operation):
            info = await result_of(plain, job)
        assert info.outcome is None and info.failure is not None and ran == []
        reason, message = {"expired": ("refused", "job expired"), "aborted": ("cancelled", "the job was cancelled"),
                           "out of tries": ("retries_exceeded", "max 3 retries exceeded")}[how]
        assert (info.failure.reason, info.failure.message) == (reason, message)
        assert await plain.zscore(QUEUE, job) is None and not await plain.hexists(RUNNING_KEY, job)

    run(redis_server, scenario)


NOT_RECORDS = {
    "a pickle": pickle.dumps({"t": 1, "f": "run_operation", "a": ("check", {"n": 1}, "x"), "k": {}}),
    "not json": b"\x80\x05}",
    "another version": json.dumps({"version": 2, "kind": "check", "body": {"n": 1}, "cache_key": "x",
                                   "enqueued_ms": 1}).encode(),
    "a field of none": json.dumps({"version": 1, "kind": "check", "body": {"n": 1}, "cache_key": "x",
                                   "enqueued_ms": 1, "function": "os.system"}).encode(),
    "another kind than its id's": json.dumps({"version": 1, "kind": "train-policy", "body": {"n": 1},
                                              "cache_key": "x", "enqueued_ms": 1}).encode(),
}


@pytest.mark.parametrize("what", sorted(NOT_RECORDS))
def test_a_job_whose_record_fails_its_schema_ends_failed_unrun_and_the_worker_goes_on(
        redis_server: RedisServer, what: str) -> None:
    ran: list[int] = []

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            ran.append(n)
            return JobEnd(done(n))

        bad, good = job_id(30), job_id(31)
        await plain.set(job_key_prefix + bad, NOT_RECORDS[what])
        await plain.zadd(QUEUE, {bad: 1})
        async with worker(redis_server, operation):
            info = await result_of(plain, bad)
            await enqueue(plain, good, 2)
            assert (await result_of(plain, good)).outcome == done(2)  # the worker goes on
        assert info.failure is not None and info.failure.reason == "refused" and ran == [2]
        assert info.failure.message.startswith("the job's record is refused:"), info.failure.message

    run(redis_server, scenario)


def test_a_job_whose_id_names_no_tenant_ends_failed_without_running(redis_server: RedisServer) -> None:
    """Its tenant would own what it stores and whose cache scope it runs in: there is no fallback for it."""
    ran: list[int] = []

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            ran.append(n)
            return JobEnd(done(n))

        await enqueue(plain, "check-nobody", 1)
        async with worker(redis_server, operation):
            info = await result_of(plain, "check-nobody")
        assert info.failure is not None and ran == []
        assert info.failure.reason == "refused" and "not a job id of this service" in info.failure.message

    run(redis_server, scenario)


def test_a_run_past_its_timeout_ends_failed(redis_server: RedisServer) -> None:
    async def scenario(plain: Redis[bytes]) -> None:
        job = job_id(4)
        await enqueue(plain, job, 1)
        async with worker(redis_server, long_run(asyncio.Event()), timeout_s=0.2):
            info = await result_of(plain, job)
        assert info.failure is not None and (info.failure.reason, info.failure.message) == ("crashed", "TimeoutError()")

    run(redis_server, scenario)


def test_a_run_a_shutdown_cancels_goes_back_to_its_queue(redis_server: RedisServer) -> None:
    started = asyncio.Event()

    async def scenario(plain: Redis[bytes]) -> None:
        job = job_id(5)
        await enqueue(plain, job, 1)
        async with worker(redis_server, long_run(started)):
            await asyncio.wait_for(started.wait(), 10)
        # cancelled by the shutdown: queued again, runnable at once, its try counted, no result, no claim
        assert await plain.zscore(QUEUE, job) is not None and not await plain.exists(result_key_prefix + job)
        assert not await plain.exists(in_progress_key_prefix + job)
        assert await plain.get(retry_key_prefix + job) == b"1"
        assert not await plain.hexists(RUNNING_KEY, job)
        async with worker(redis_server):
            info = await result_of(plain, job)
        assert info.outcome is not None and info.job_try == 2

    run(redis_server, scenario)


def test_a_run_whose_end_redis_refused_is_handed_back_by_the_next_beat(redis_server: RedisServer) -> None:
    """The end could not be recorded (Redis refused the script): the run's claim moves to the dropped ones,
    and the worker's next beat hands the job back to the queue."""
    claims = RunClaims("w1", heartbeat, 5.0)

    async def scenario(plain: Redis[bytes]) -> None:
        async def operation(ctx: JobContext, n: int) -> JobEnd:
            await plain.config_set("maxmemory", 1)  # noeviction refuses every write from here
            return JobEnd(done(n))

        job = job_id(6)
        await enqueue(plain, job, 1)
        async with worker(redis_server, operation, claims=claims):
            deadline = asyncio.get_running_loop().time() + 10
            while not claims.dropped:
                assert asyncio.get_running_loop().time() < deadline, "the unrecorded run was never dropped"
                await asyncio.sleep(0.02)
        await plain.config_set("maxmemory", 0)
        assert await plain.exists(in_progress_key_prefix + job)  # started, never ended: nothing else frees it
        released = await beat(plain, heartbeat(), 5.0, dropped=set(claims.dropped))
        assert released == [job] and not await plain.exists(in_progress_key_prefix + job)
        async with worker(redis_server):
            assert (await result_of(plain, job)).outcome is not None

    run(redis_server, scenario)


TAKE = steps.Take(QUEUE, "w1", read_limit=4, in_progress_ms=300_000)


async def take(redis: Redis[bytes], claim: steps.Claim | None, skip: list[str]) -> Any:
    return await steps.take(redis, TAKE, 2**45, claim, skip)


def test_a_take_whose_answer_was_lost_is_handed_back_by_the_next_beat(redis_server: RedisServer) -> None:
    """The take's script ran, its answer never came (the connection broke): the worker never learned which
    job its claim names, yet the next beat hands that job back."""
    claims = RunClaims("w1", heartbeat, 5.0)

    async def scenario(plain: Redis[bytes]) -> None:
        job = job_id(8)
        await enqueue(plain, job, 1)
        claim = claims.open()
        assert (await take(plain, claim, []))[1] is not None  # answer "lost"
        claims.lost(claim.token)
        assert await plain.exists(in_progress_key_prefix + job)
        released = await beat(plain, heartbeat(), 5.0, dropped=set(claims.dropped))
        assert released == [job] and not await plain.hexists(RUNNING_KEY, job)
        async with worker(redis_server):
            info = await result_of(plain, job)
        assert info.outcome is not None and info.job_try == 2  # the lost take counted as a try, as every start counts

    run(redis_server, scenario)


def test_the_next_job_taken_skips_tenants_at_their_share_and_jobs_already_started(redis_server: RedisServer) -> None:
    claims = RunClaims("w1", heartbeat, 5.0)

    async def scenario(plain: Redis[bytes]) -> None:
        busy, other = "aaaaaaaaaaaaaaaa", "bbbbbbbbbbbbbbbb"
        first, second, third = job_id(9, busy), job_id(10, busy), job_id(11, other)
        for score, job in enumerate((first, second, third), start=1):  # fair scores, ascending
            await enqueue(plain, job, 1)
            await plain.zadd(QUEUE, {job: score})
        _, taken, more = await take(plain, claims.open(), [])
        assert taken is not None and taken.id == first and more
        _, taken, _ = await take(plain, claims.open(), [busy])  # `busy` at its share: `other` next
        assert taken is not None and taken.id == third
        _, taken, _ = await take(plain, claims.open(), [])  # the started ones stay queued, untaken
        assert taken is not None and taken.id == second
        assert (await take(plain, claims.open(), []))[1] is None
        await plain.zadd(abort_jobs_ss, {second: 1})
        assert (await take(plain, None, [])) == ([second.encode()], None, False)  # marks, no take

    run(redis_server, scenario)


def test_a_running_job_marked_for_abort_is_cancelled_and_ends_so(redis_server: RedisServer) -> None:
    started = asyncio.Event()

    async def scenario(plain: Redis[bytes]) -> None:
        job = job_id(12)
        await enqueue(plain, job, 1)
        async with worker(redis_server, long_run(started)):
            await asyncio.wait_for(started.wait(), 10)
            await steps.mark_abort(plain, QUEUE, job, 1)  # as the gateway's cancel marks a running job
            info = await result_of(plain, job)
        assert info.failure is not None and info.failure.reason == "cancelled"
        assert await plain.zscore(abort_jobs_ss, job) is None

    run(redis_server, scenario)


def test_a_worker_whose_wake_channel_dropped_subscribes_again(redis_server: RedisServer,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Its polls are a minute apart here, so only the gateway's notice can start the job at once: after Redis
    dropped the subscription, the worker subscribes again and is woken by the next notice."""
    monkeypatch.setattr(queue_worker, "SAFETY_POLL_S", 60.0)
    monkeypatch.setattr(queue_worker, "RESUBSCRIBE_S", 0.1)

    async def scenario(plain: Redis[bytes]) -> None:
        async with worker(redis_server, idle_poll_s=60.0) as running:
            await wait_for(lambda: running.subscribed)
            await plain.execute_command("CLIENT", "KILL", "TYPE", "pubsub")
            await wait_for(lambda: not running.subscribed)
            await wait_for(lambda: running.subscribed)
            job = job_id(13)
            await enqueue(plain, job, 4)
            await plain.publish(wake_channel(QUEUE), b"1")  # as the gateway's submission does
            info = await result_of(plain, job, timeout_s=20)
        assert info.outcome == done(4)

    run(redis_server, scenario)


async def wait_for(predicate: Callable[[], bool], timeout_s: float = 10) -> None:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not predicate():
        assert asyncio.get_running_loop().time() < deadline, "never happened"
        await asyncio.sleep(0.02)
