"""Submitting, watching and cancelling jobs on arq queues, and reading their state back as `JobStatus`.

arq does the queueing (at-least-once delivery, job-id de-duplication, abort); this module adds what arq
leaves to its user: a bound on queue length, progress next to the job, and re-running an id whose last run
was cancelled or crashed (arq would otherwise keep answering with that old result, see arq#485). A job is
written exactly as arq's `enqueue_job` writes it, but in one script with its bound, its tenant's fair place and
the worker's wake-up (`_SUBMIT`): one round trip instead of eight on the check's hot path.
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
from arq.jobs import Job, JobResult, deserialize_result, serialize_job, serialize_result
from arq.utils import timestamp_ms, to_ms
from arq.worker import JobExecutionFailed

from precond.gateway.completions import Completions, Watch
from precond.gateway.errors import bounded
from precond.gateway.quotas import (
    FAIR_EPOCH_MS,
    FAIR_SCORE_FUNCTION,
    JOB_EXPIRY,
    STATE_TTL_S,
    TENANT_JOBS_FUNCTION,
    fair_key,
    tenant_jobs_key,
)
from precond.jobs.cache import ResultCache
from precond.jobs.keys import JOB_FUNCTION, kind_of, progress_key, wake_channel
from precond.jobs.kinds import KINDS, queue_for, queues_of
from precond.jobs.notices import NOTIFY_FUNCTION, WAITERS_TTL_S, waiters_key
from precond.jobs.records import Outcome, parse_progress
from precond.jobs.scripts import LuaScript
from precond_client.schemas.api import ErrorInfo, JobKind, JobProgress, JobStatus

SAFETY_POLL_S = 1.0
"""How often a waiting request re-reads its job even while completion notices work (a notice can be lost)."""


_SUBMIT = LuaScript("#!lua\n" + FAIR_SCORE_FUNCTION + TENANT_JOBS_FUNCTION + """
local full = tenant_full(KEYS[6], ARGV[1], ARGV[9], ARGV[10])
if full >= 0 then return -2 - full end
if redis.call('exists', KEYS[4]) == 1 then return 0 end
if redis.call('exists', KEYS[3]) == 1 then
  redis.call('sadd', KEYS[7], ARGV[12])
  redis.call('expire', KEYS[7], ARGV[13])
  return 0
end
if redis.call('zcard', KEYS[1]) >= tonumber(ARGV[2]) then return -1 end
redis.call('zrem', KEYS[5], ARGV[1])
local score = fair_score(KEYS[1], KEYS[2], ARGV[3], ARGV[4], ARGV[5])
redis.call('psetex', KEYS[3], ARGV[7], ARGV[6])
redis.call('zadd', KEYS[1], score, ARGV[1])
redis.call('zadd', KEYS[6], ARGV[11], ARGV[1])
redis.call('expire', KEYS[6], ARGV[5])
redis.call('sadd', KEYS[7], ARGV[12])
redis.call('expire', KEYS[7], ARGV[13])
redis.call('publish', ARGV[8], '1')
return 1
""")
"""Enqueue a job as arq's `enqueue_job` would (its job key, its place in the queue), in one step with everything
around it: `-2 - n` when its tenant has `n` jobs queued or running, its cap (service.quotas); 0 when the same job
exists (queued, running or with a result: identical requests share it); -1 when the queue holds `max_jobs`
already; else 1. The step counts the job as its tenant's, clears a stale abort mark of the id (arq#485), gives
the job its tenant's fair place (service.quotas), names this gateway process among the job's waiters (unless
its end is stored already: precond/jobs/notices.py) and wakes an idle worker (advisory: workers still poll).
Atomic, so concurrent submissions, from any number of gateway processes, never push a queue or a tenant past
its bound. Declared (`#!lua`, Redis 7), so a Redis at its `maxmemory` refuses the whole step before it starts
(503); undeclared, Redis refuses only a script whose first write needs memory, and a first write that frees
some (a stale abort mark, a finished job's place in its tenant's set) let the rest enqueue past the limit."""

_CANCEL_QUEUED = NOTIFY_FUNCTION + """
if redis.call('exists', KEYS[3]) == 1 or redis.call('exists', KEYS[5]) == 1 then return 0 end
if redis.call('zrem', KEYS[1], ARGV[1]) == 0 then return 0 end
redis.call('del', KEYS[2], KEYS[4])
redis.call('zrem', KEYS[6], ARGV[1])
redis.call('set', KEYS[3], ARGV[4], 'PX', ARGV[5])
redis.call('set', KEYS[5], ARGV[2], 'PX', ARGV[3])
notify(KEYS[7], ARGV[1])
return 1
"""
"""Cancel a job no worker has started, at once: out of its queue, its result `cancelled`, its waiters told. The
in-progress key is set briefly to a guard value, so that a worker's take (precond/worker/queue_worker.py), which starts
only jobs without one, cannot start it."""

_DROP_GUARD = """
if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end
return 0
"""
CANCEL_GUARD = b"cancelled"
CANCEL_GUARD_MS = 2000


class QueueFull(Exception):
    """The job's queue holds `max_jobs` already; the client should come back later (429)."""


class TenantFull(Exception):
    """The tenant has its cap of jobs queued or running (`count` of them); it should come back later (429)."""

    def __init__(self, count: int) -> None:
        super().__init__(count)
        self.count = count


class JobQueue:
    def __init__(
        self, redis: ArqRedis, cache: ResultCache, completions: Completions, max_jobs: int, tenant_max_jobs: int,
        result_ttl_s: int = 3600,
    ) -> None:
        self.redis = redis
        self.cache = cache
        self.completions = completions
        self.max_jobs = max_jobs
        self.tenant_max_jobs = tenant_max_jobs
        self.result_ttl_s = result_ttl_s

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

    async def submit(self, kind: JobKind, job_id: str, body: dict[str, Any], tenant_tag: str, cache_key: str,
                     timeout_s: float, poll_s: float) -> JobStatus | None:
        """Enqueue unless the same job exists, then wait for it (`_wait`). Identical requests share the job
        already there, unless its last run says nothing final (cancelled, crashed: `_last_run_unusable`), which
        is run again. TenantFull or QueueFull past a bound. The job's result is cached under `cache_key`."""
        queue = queue_for(kind, body)
        with self.completions.watch(job_id) as watch:  # before the enqueue: its notice cannot come first
            enqueued = await self._enqueue(kind, job_id, body, tenant_tag, cache_key, queue)
            if not enqueued and await self._last_run_unusable(self._job(job_id, queue)):
                await self.redis.delete(result_key_prefix + job_id)
                await self.redis.eval(_DROP_GUARD, 1, in_progress_key_prefix + job_id, CANCEL_GUARD)  # type: ignore[no-untyped-call]
                enqueued = await self._enqueue(kind, job_id, body, tenant_tag, cache_key, queue)
            return await self._wait(job_id, timeout_s, poll_s, watch, read_first=not enqueued)

    async def _enqueue(self, kind: JobKind, job_id: str, body: dict[str, Any], tenant_tag: str, cache_key: str,
                       queue: str) -> bool:
        """One round trip (`_SUBMIT`): True when enqueued, False when the same job exists; TenantFull, QueueFull."""
        now = timestamp_ms()
        job = serialize_job(JOB_FUNCTION, (kind, body, cache_key), {}, None, now, serializer=self.redis.job_serializer)
        enqueued = int(await _SUBMIT(
            self.redis,
            [queue, fair_key(queue), job_key_prefix + job_id, result_key_prefix + job_id, abort_jobs_ss,
             tenant_jobs_key(tenant_tag), waiters_key(job_id)],
            [job_id, self.max_jobs, tenant_tag, FAIR_EPOCH_MS, STATE_TTL_S, job, to_ms(JOB_EXPIRY), wake_channel(queue),
             self.tenant_max_jobs, job_key_prefix, now / 1000, self.completions.channel, WAITERS_TTL_S],
        ))
        if enqueued <= -2:
            raise TenantFull(-2 - enqueued)
        if enqueued < 0:
            raise QueueFull(queue)
        return enqueued == 1

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
        if raw_result:
            return _ended(job_id, kind, raw_result, raw_progress)
        progress = parse_progress(raw_progress)
        if not in_progress and score is None:
            cached = await self.cache.get(job_id)
            if cached is None:
                return None
            return JobStatus(
                id=job_id, kind=kind, status="succeeded", progress=_done(progress), result=cached
            )
        return JobStatus(id=job_id, kind=kind, status="running" if in_progress else "queued", progress=progress)

    async def _wait(self, job_id: str, timeout_s: float, poll_s: float, watch: Watch,
                    read_first: bool) -> JobStatus | None:
        """The job's status once finished, or its current status when `timeout_s` runs out first. Woken by the
        job's completion notice (`watch`), whose end, when it carries one, is the answer without a read; polls
        every `poll_s` only while notices are unavailable. `read_first=False` for a job this request just
        enqueued: it is queued, so the first read waits for its notice (or the fallback poll) instead of
        spending a round trip."""
        deadline = time.monotonic() + timeout_s
        status = None
        if not read_first:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(watch.event.wait(), min(timeout_s, self._interval(poll_s)))
        kind = kind_of(job_id)
        while True:
            if watch.end is not None and kind is not None:
                return _ended(job_id, kind, watch.end[1], watch.end[0])
            watch.event.clear()  # before reading: a notice that lands after the read still wakes us
            status = await self.status(job_id)
            if status is None or status.status in ("succeeded", "failed", "cancelled"):
                return status
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return status
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(watch.event.wait(), min(remaining, self._interval(poll_s)))

    def _interval(self, poll_s: float) -> float:
        return SAFETY_POLL_S if self.completions.subscribed else poll_s

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
        async with self.redis.pipeline(transaction=False) as pipe:  # the mark, and its worker woken to read it
            pipe.zadd(abort_jobs_ss, {job_id: timestamp_ms()})
            pipe.publish(wake_channel(queue), b"1")
            await pipe.execute()
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
            _CANCEL_QUEUED, 7, queue, job_key_prefix + job_id, in_progress_key_prefix + job_id,
            retry_key_prefix + job_id, result_key_prefix + job_id, abort_jobs_ss, waiters_key(job_id),
            job_id, result, self.result_ttl_s * 1000, CANCEL_GUARD, CANCEL_GUARD_MS,
        )
        return bool(done)


def _ended(job_id: str, kind: JobKind, raw_result: bytes, raw_progress: bytes | None) -> JobStatus:
    """A job's state from its stored end (arq's result) and progress, as read back or as its notice carried it."""
    progress = parse_progress(raw_progress or None)
    state, result, error = _state(deserialize_result(raw_result))
    done = _done(progress) if state == "succeeded" else progress
    return JobStatus(id=job_id, kind=kind, status=state, progress=done, result=result, error=error)


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
