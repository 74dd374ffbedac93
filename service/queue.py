"""Submitting, watching and cancelling jobs on arq queues, and reading their state back as `JobStatus`.

arq does the queueing (at-least-once delivery, `_job_id` de-duplication, abort); this module adds what arq
leaves to its user: a bound on queue length, progress next to the job, and re-running an id whose last run
was cancelled or crashed (arq would otherwise keep answering with that old result, see arq#485).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from arq.connections import ArqRedis
from arq.constants import (
    abort_jobs_ss,
    in_progress_key_prefix,
    job_key_prefix,
    result_key_prefix,
    retry_key_prefix,
)
from arq.jobs import Job, JobResult, deserialize_result, serialize_result
from arq.jobs import JobStatus as ArqStatus
from arq.worker import JobExecutionFailed
from redis.exceptions import RedisError

from jobs.cache import ResultCache
from jobs.keys import JOB_FUNCTION, done_channel, kind_of, progress_key, wake_channel
from jobs.kinds import KINDS, queue_for, queues_of
from jobs.records import Outcome, parse_progress
from schemas.api import ErrorInfo, JobKind, JobProgress, JobStatus
from service.completions import Completions
from service.errors import bounded
from service.quotas import JOB_EXPIRY, Quotas

SAFETY_POLL_S = 1.0
"""How often a waiting request re-reads its job even while completion notices work (a notice can be lost)."""


_UNDO_OVER_BOUND = """
local queued = redis.call('zscore', KEYS[1], ARGV[1])
if queued and redis.call('zcard', KEYS[1]) > tonumber(ARGV[2]) and redis.call('exists', KEYS[3]) == 0 then
  redis.call('zrem', KEYS[1], ARGV[1])
  redis.call('del', KEYS[2])
  return 1
end
return 0
"""


_CANCEL_QUEUED = """
if redis.call('exists', KEYS[3]) == 1 or redis.call('exists', KEYS[5]) == 1 then return 0 end
if redis.call('zrem', KEYS[1], ARGV[1]) == 0 then return 0 end
redis.call('del', KEYS[2], KEYS[4])
redis.call('zrem', KEYS[6], ARGV[1])
redis.call('set', KEYS[3], ARGV[4], 'PX', ARGV[5])
redis.call('set', KEYS[5], ARGV[2], 'PX', ARGV[3])
return 1
"""
"""Cancel a job no worker has started, at once: out of its queue, its result `cancelled`. The in-progress key
is set briefly to a guard value, so a worker that read the id from the queue just before cannot start it
(arq WATCHes that key between reading the queue and claiming the job)."""

_DROP_GUARD = """
if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end
return 0
"""
CANCEL_GUARD = b"cancelled"
CANCEL_GUARD_MS = 2000


class QueueFull(Exception):
    """The job's queue holds `max_jobs` already; the client should come back later (429)."""


class JobQueue:
    def __init__(
        self, redis: ArqRedis, cache: ResultCache, completions: Completions, max_jobs: int, quotas: Quotas,
        result_ttl_s: int = 3600,
    ) -> None:
        self.redis = redis
        self.cache = cache
        self.completions = completions
        self.max_jobs = max_jobs
        self.quotas = quotas
        self.result_ttl_s = result_ttl_s
        self._admissions: dict[str, asyncio.Lock] = {}  # one per queue (a handful: jobs.kinds.KINDS)

    def _job(self, job_id: str, queue: str) -> Job:
        return Job(job_id, self.redis, _queue_name=queue)

    async def _queue_of(self, job_id: str, kind: JobKind) -> str:
        """The queue holding the job (an inference goes to one of two, by cost); its kind's default when
        it is in none (running or finished: arq needs the queue only to tell queued from unknown)."""
        queues = queues_of(kind)
        if len(queues) > 1:
            async with self.redis.pipeline(transaction=False) as pipe:
                for queue in queues:
                    pipe.zscore(queue, job_id)
                scores = await pipe.execute()
            for queue, score in zip(queues, scores, strict=True):
                if score is not None:
                    return queue
        return KINDS[kind].queue

    async def depth(self, queue: str) -> int:
        return int(await self.redis.zcard(queue))

    async def submit(self, kind: JobKind, job_id: str, body: dict[str, Any], tenant_tag: str, cache_key: str) -> None:
        """Enqueue unless the same job exists: identical requests then share the one already there. The
        job's place in its queue is its tenant's fair start (service.quotas), and its result is cached
        under `cache_key`. One admission per queue at a time in this process: the depth check and the
        enqueue are then one step for its requests, so the queue overshoots its bound only by what other
        gateway processes enqueue at the same instant (and `_over_bound` takes those back)."""
        queue = queue_for(kind, body)
        async with self._admissions.setdefault(queue, asyncio.Lock()):
            enqueued = await self._admit(kind, job_id, body, tenant_tag, cache_key, queue)
        if enqueued:  # wake an idle worker now rather than at its next poll; advisory: workers still poll
            with contextlib.suppress(RedisError, OSError):
                await self.redis.publish(wake_channel(queue), b"1")

    async def _admit(self, kind: JobKind, job_id: str, body: dict[str, Any], tenant_tag: str, cache_key: str,
                     queue: str) -> bool:
        """Enqueue (True), or find the same job already there (False); QueueFull past the bound."""
        job = self._job(job_id, queue)
        if await self.depth(queue) >= self.max_jobs and await self._arq_status(job_id, queue) == ArqStatus.not_found:
            raise QueueFull(queue)
        enqueued = await self._enqueue(kind, job_id, body, tenant_tag, cache_key)
        if enqueued is None and await self._last_run_unusable(job):
            await self.redis.delete(result_key_prefix + job_id)
            await self.redis.eval(_DROP_GUARD, 1, in_progress_key_prefix + job_id, CANCEL_GUARD)  # type: ignore[no-untyped-call]
            enqueued = await self._enqueue(kind, job_id, body, tenant_tag, cache_key)
        if enqueued is not None and await self._over_bound(queue, job_id):
            raise QueueFull(queue)
        return enqueued is not None

    async def _over_bound(self, queue: str, job_id: str) -> bool:
        """Take back a job that concurrent submissions pushed past the bound (the depth check above is not
        atomic with the enqueue: 48 clients at once all saw a short queue). By the count after our own enqueue,
        not by rank: a fair score is handed out before its job is enqueued, so ranks seen by racing submissions
        can all look in bounds. Racing jobs may each refuse themselves (a 429 too many, never a queue too long);
        a job a worker already started is left alone."""
        undone = await self.redis.eval(  # type: ignore[no-untyped-call]
            _UNDO_OVER_BOUND, 3, queue, job_key_prefix + job_id, in_progress_key_prefix + job_id,
            job_id, self.max_jobs,
        )
        return bool(undone)

    async def _enqueue(self, kind: JobKind, job_id: str, body: dict[str, Any], tenant_tag: str,
                       cache_key: str) -> Job | None:
        await self.redis.zrem(abort_jobs_ss, job_id)
        queue = queue_for(kind, body)
        start = await self.quotas.fair_start(queue, tenant_tag)
        return await self.redis.enqueue_job(
            JOB_FUNCTION, kind, body, cache_key, _job_id=job_id, _queue_name=queue, _defer_until=start,
            _expires=JOB_EXPIRY,
        )

    async def _last_run_unusable(self, job: Job) -> bool:
        info = await job.result_info()
        return info is not None and _is_internal(info)

    async def status(self, job_id: str) -> JobStatus | None:
        """The job's state, read in one round trip once its queue is known (result, progress and arq's marks
        together: a waiting request reads it at least twice)."""
        kind = kind_of(job_id)
        if kind is None:
            return None
        queue = await self._queue_of(job_id, kind)
        async with self.redis.pipeline(transaction=False) as pipe:
            pipe.get(result_key_prefix + job_id)
            pipe.get(progress_key(job_id))
            pipe.exists(in_progress_key_prefix + job_id)
            pipe.zscore(queue, job_id)
            raw_result, raw_progress, in_progress, score = await pipe.execute()
        progress = parse_progress(raw_progress)
        if raw_result:
            state, result, error = _state(deserialize_result(raw_result))
            done = _done(progress) if state == "succeeded" else progress
            return JobStatus(id=job_id, kind=kind, status=state, progress=done, result=result, error=error)
        if not in_progress and score is None:
            cached = await self.cache.get(job_id)
            if cached is None:
                return None
            return JobStatus(
                id=job_id, kind=kind, status="succeeded", progress=_done(progress), result=cached
            )
        return JobStatus(id=job_id, kind=kind, status="running" if in_progress else "queued", progress=progress)

    async def _arq_status(self, job_id: str, queue: str) -> ArqStatus:
        """arq's `Job.status` without its MULTI: Redis refuses every command queued in a transaction while it
        is over `maxmemory`, and a full queue Redis (noeviction) must still show clients their jobs."""
        async with self.redis.pipeline(transaction=False) as pipe:
            pipe.exists(result_key_prefix + job_id)
            pipe.exists(in_progress_key_prefix + job_id)
            pipe.zscore(queue, job_id)
            complete, in_progress, score = await pipe.execute()
        if complete:
            return ArqStatus.complete
        if in_progress:
            return ArqStatus.in_progress
        return ArqStatus.not_found if score is None else ArqStatus.queued

    async def wait(self, job_id: str, timeout_s: float, poll_s: float) -> JobStatus | None:
        """The job's status once finished, or its current status when `timeout_s` runs out first.

        Woken by the job's completion notice; polls every `poll_s` only while notices are unavailable.
        """
        deadline = time.monotonic() + timeout_s
        with self.completions.watch(job_id) as announced:
            while True:
                announced.clear()  # before reading: a notice that lands after the read still wakes us
                status = await self.status(job_id)
                if status is None or status.status in ("succeeded", "failed", "cancelled"):
                    return status
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return status
                interval = SAFETY_POLL_S if self.completions.subscribed else poll_s
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(announced.wait(), min(remaining, interval))

    async def cancel(self, job_id: str, confirm_s: float) -> JobStatus | None:
        """Cancel a queued or running job; the answer says `cancelled` once it took effect.

        A queued job is taken out of its queue here, at once (a busy worker would see arq's abort mark only
        when it next starts a job). A running one gets arq's abort: the worker cancels it, the engine stops at
        its next check (between decode steps, and every sandbox call is interrupted), and arq records it;
        this waits up to `confirm_s` for that. Only existing unfinished jobs are marked: an abort mark for an
        unknown id would stay in arq's abort set and kill the next job that gets this id (arq#485).
        """
        status = await self.status(job_id)
        if status is None or status.status not in ("queued", "running"):
            return status
        queue = await self._queue_of(job_id, status.kind)
        if status.status == "queued" and await self._cancel_queued(job_id, status.kind, queue):
            return await self.status(job_id)
        job = self._job(job_id, queue)
        with contextlib.suppress(TimeoutError):
            await job.abort(timeout=confirm_s, poll_delay=min(0.1, confirm_s / 4))
        return await self.status(job_id)

    async def _cancel_queued(self, job_id: str, kind: JobKind, queue: str) -> bool:
        now = int(time.time() * 1000)
        result = serialize_result(
            JOB_FUNCTION, (kind,), {}, 0, now, False, asyncio.CancelledError(), now, now,
            f"{job_id}:{JOB_FUNCTION}", queue, job_id,
        )
        done = await self.redis.eval(  # type: ignore[no-untyped-call]
            _CANCEL_QUEUED, 6, queue, job_key_prefix + job_id, in_progress_key_prefix + job_id,
            retry_key_prefix + job_id, result_key_prefix + job_id, abort_jobs_ss,
            job_id, result, self.result_ttl_s * 1000, CANCEL_GUARD, CANCEL_GUARD_MS,
        )
        if done:
            with contextlib.suppress(RedisError, OSError):
                await self.redis.publish(done_channel(job_id), b"1")
        return bool(done)


def _done(progress: JobProgress) -> JobProgress:
    """A finished job's progress: complete, whatever the last (advisory, asynchronous) report said."""
    total = max(progress.total, 1)
    return JobProgress(phase="done", done=total, total=total)


NOT_REUSABLE = frozenset({"internal", "resource_limit", "sandbox_failure"})


def _is_internal(info: JobResult) -> bool:
    """Cancelled or crashed runs, and runs stopped by a sandbox limit or a sandbox failure, say nothing
    final about the request, so they must not stand in for its result: the next identical request runs."""
    if not info.success:
        return True
    error = Outcome.from_arq(info.result).error
    return error is not None and error.type in NOT_REUSABLE


def _state(info: JobResult) -> tuple[Any, dict[str, Any] | None, ErrorInfo | None]:
    """arq's stored result as (state, result, error): workers return outcomes, arq stores their exceptions."""
    if info.success:
        outcome = Outcome.from_arq(info.result)
        return outcome.status, outcome.result, None if outcome.error is None else bounded(outcome.error)
    if isinstance(info.result, asyncio.CancelledError):
        return "cancelled", None, ErrorInfo(type="cancelled", message="the job was cancelled")
    if isinstance(info.result, JobExecutionFailed) and "retries exceeded" in str(info.result):
        return "failed", None, ErrorInfo(type="internal", message=(
            f"the job was started {info.job_try - 1} times (PRECOND_JOB_MAX_TRIES) and its worker never finished "
            "it (it died or was stopped each time); it is not run again"))
    return "failed", None, bounded(ErrorInfo(type="internal", message=f"job failed: {info.result!r}"))
