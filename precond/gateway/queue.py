"""Submitting, watching and cancelling jobs, and reading their state back as `JobStatus`.

Each write is a step of the queue's contract (`precond.jobs.queue.steps`): submit (bound, fair place, enqueue,
waiter and wake-up in one round trip), cancel a queued job, mark a running one for abort. What this module adds is
the waiting: a job's completion notice (`Completions`), a fallback read, and re-running an id whose last run was
cancelled or crashed (its stored end would otherwise keep answering, arq#485).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from redis.asyncio import Redis

from precond.gateway.completions import Completions, Watch
from precond.gateway.errors import bounded
from precond.jobs.cache import ResultCache
from precond.jobs.queue import steps
from precond.jobs.queue.keys import IN_PROGRESS_PREFIX, RESULT_PREFIX, JobId, progress_key
from precond.jobs.queue.kinds import KINDS, queue_for, queues_of
from precond.jobs.queue.payloads import (
    EndRecord,
    RecordError,
    cancelled_end,
    decode_end,
    decode_progress,
    encode_job,
)
from precond_client.schemas import ErrorInfo, JobProgress, JobStatus

SAFETY_POLL_S = 1.0
"""How often a waiting request re-reads its job even while completion notices work (a notice can be lost)."""


class JobQueue:
    def __init__(
        self, redis: Redis[bytes], cache: ResultCache, completions: Completions, max_jobs: int, tenant_max_jobs: int,
        result_ttl_s: int = 3600,
    ) -> None:
        self.redis = redis
        self.cache = cache
        self.completions = completions
        self.max_jobs = max_jobs
        self.tenant_max_jobs = tenant_max_jobs
        self.result_ttl_s = result_ttl_s

    async def _queue_of(self, job: JobId) -> str:
        """The queue holding the job (an inference goes to one of two, by cost); its kind's default when
        it is in none (running or finished: the queue is needed only to tell queued from unknown)."""
        queues = queues_of(job.kind)
        if len(queues) > 1:
            async with self.redis.pipeline(transaction=False) as pipe:
                for queue in queues:
                    pipe.zscore(queue, job.value)
                scores = await pipe.execute()
            for queue, score in zip(queues, scores, strict=True):
                if score is not None:
                    return queue
        return KINDS[job.kind].queue

    async def depth(self, queue: str) -> int:
        return int(await self.redis.zcard(queue))

    async def submit(self, job: JobId, body: dict[str, Any], cache_key: str, timeout_s: float, poll_s: float
                     ) -> JobStatus | None:
        """Enqueue unless the same job exists, then wait for it (`_wait`). Identical requests share the job
        already there, unless its last run says nothing final (cancelled, crashed: `_last_run_unusable`), which
        is run again. TenantFull or QueueFull past a bound. The job's result is cached under `cache_key`."""
        queue = queue_for(job.kind, body)
        with self.completions.watch(job.value) as watch:  # before the enqueue: its notice cannot come first
            enqueued = await self._enqueue(job, body, cache_key, queue)
            if not enqueued and await self._last_run_unusable(job):
                await steps.reopen(self.redis, job.value)
                enqueued = await self._enqueue(job, body, cache_key, queue)
            return await self._wait(job, timeout_s, poll_s, watch, read_first=not enqueued)

    async def _enqueue(self, job: JobId, body: dict[str, Any], cache_key: str, queue: str) -> bool:
        """One round trip (`steps.submit`): True when enqueued, False when the same job exists; TenantFull,
        QueueFull."""
        now = int(time.time() * 1000)
        submission = steps.Submission(queue, job.value, job.tenant, encode_job(job.kind, body, cache_key, now), now,
                                      self.completions.channel)
        return await steps.submit(self.redis, submission, self.max_jobs, self.tenant_max_jobs)

    async def _last_run_unusable(self, job: JobId) -> bool:
        raw = await self.redis.get(RESULT_PREFIX + job.value)
        if raw is None:
            return False
        try:
            return _is_internal(decode_end(raw))
        except RecordError:
            return True  # not an end this service wrote: run the job again

    async def status(self, job: JobId) -> JobStatus | None:
        """The job's state, read in one round trip once its queue is known (result, progress and the in-progress
        mark together: a waiting request reads it at least twice)."""
        queue = await self._queue_of(job)
        async with self.redis.pipeline(transaction=False) as pipe:
            pipe.get(RESULT_PREFIX + job.value)
            pipe.get(progress_key(job.value))
            pipe.exists(IN_PROGRESS_PREFIX + job.value)
            pipe.zscore(queue, job.value)
            raw_result, raw_progress, in_progress, score = await pipe.execute()
        if raw_result:
            return _ended(job, raw_result, raw_progress)
        progress = decode_progress(raw_progress)
        if not in_progress and score is None:
            cached = await self.cache.get(job.value)
            if cached is None:
                return None
            return JobStatus(
                id=job.value, kind=job.kind, status="succeeded", progress=_done(progress), result=cached
            )
        return JobStatus(id=job.value, kind=job.kind, status="running" if in_progress else "queued",
                         progress=progress)

    async def _wait(self, job: JobId, timeout_s: float, poll_s: float, watch: Watch,
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
        while True:
            if watch.end is not None:
                return _ended(job, watch.end[1], watch.end[0])
            watch.event.clear()  # before reading: a notice that lands after the read still wakes us
            status = await self.status(job)
            if status is None or status.status in ("succeeded", "failed", "cancelled"):
                return status
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return status
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(watch.event.wait(), min(remaining, self._interval(poll_s)))

    def _interval(self, poll_s: float) -> float:
        return SAFETY_POLL_S if self.completions.subscribed else poll_s

    async def cancel(self, job: JobId, confirm_s: float) -> JobStatus | None:
        """Cancel a queued or running job; the answer says `cancelled` once it took effect.

        A queued job is taken out of its queue here, at once (a busy worker would see the abort mark only
        when it next starts a job). A running one is marked for abort: the worker cancels it, the engine stops
        at its next check (between decode steps, and every sandbox call is interrupted), and its end is stored
        as cancelled; this waits up to `confirm_s` for that. Only existing unfinished jobs are marked: an abort
        mark for an unknown id would stay in the abort set and kill the next job that gets this id (arq#485).
        """
        status = await self.status(job)
        if status is None or status.status not in ("queued", "running"):
            return status
        queue = await self._queue_of(job)
        if status.status == "queued" and await self._cancel_queued(job, queue):
            return await self.status(job)
        await steps.mark_abort(self.redis, queue, job.value, int(time.time() * 1000))
        deadline = time.monotonic() + confirm_s
        while status is not None and status.status in ("queued", "running") and time.monotonic() < deadline:
            await asyncio.sleep(min(0.1, confirm_s / 4))
            status = await self.status(job)
        return status

    async def _cancel_queued(self, job: JobId, queue: str) -> bool:
        cancelled = cancelled_end(job.value, queue, int(time.time() * 1000))
        return await steps.cancel_queued(self.redis, queue, job.value, cancelled, self.result_ttl_s * 1000)


def _ended(job: JobId, raw_result: bytes, raw_progress: bytes | None) -> JobStatus:
    """A job's state from its stored end and progress, as read back or as its notice carried it."""
    progress = decode_progress(raw_progress)
    try:
        state, result, error = _state(decode_end(raw_result))
    except RecordError as exc:
        state, result, error = "failed", None, bounded(ErrorInfo(
            type="internal", message=f"the job's stored end is not a record this service reads: {exc}"))
    done = _done(progress) if state == "succeeded" else progress
    return JobStatus(id=job.value, kind=job.kind, status=state, progress=done, result=result, error=error)


def _done(progress: JobProgress) -> JobProgress:
    """A finished job's progress: complete, whatever the last (advisory, asynchronous) report said."""
    total = max(progress.total, 1)
    return JobProgress(phase="done", done=total, total=total)


NOT_REUSABLE = frozenset({"internal", "resource_limit", "sandbox_failure"})


def _is_internal(end: EndRecord) -> bool:
    """Cancelled or crashed runs, and runs stopped by a sandbox limit or a sandbox failure, say nothing
    final about the request, so they must not stand in for its result: the next identical request runs."""
    if end.outcome is None:
        return True
    return end.outcome.error is not None and end.outcome.error.type in NOT_REUSABLE


def _state(end: EndRecord) -> tuple[Any, dict[str, Any] | None, ErrorInfo | None]:
    """A stored end as (state, result, error): an outcome the job returned, or why it ended without one."""
    if end.outcome is not None:
        outcome = end.outcome
        return outcome.status, outcome.result, None if outcome.error is None else bounded(outcome.error)
    assert end.failure is not None  # an end has one or the other (EndRecord)
    if end.failure.reason == "cancelled":
        return "cancelled", None, ErrorInfo(type="cancelled", message="the job was cancelled")
    if end.failure.reason == "retries_exceeded":
        return "failed", None, ErrorInfo(type="internal", message=(
            f"the job was started {end.job_try - 1} times (PRECOND_JOB_MAX_TRIES) and its worker never finished "
            "it (it died or was stopped each time); it is not run again"))
    return "failed", None, bounded(ErrorInfo(type="internal", message=f"job failed: {end.failure.message}"))
