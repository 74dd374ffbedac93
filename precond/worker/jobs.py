"""The job function: run one engine operation in a thread, report its progress, cache its result.

The engine is CPU-bound and synchronous; running it in a thread keeps the worker's event loop free for
the queue's polling, abort checks and the heartbeat. Cancellation crosses the thread boundary as a predicate the
engine polls between steps.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Awaitable, Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from functools import partial
from typing import Any, Final

from pydantic import BaseModel
from redis.asyncio import Redis

from precond.engine.engine import Engine
from precond.engine.scope import scoped
from precond.jobs.cache import ResultCache
from precond.jobs.queue.keys import JobId, is_shared
from precond.jobs.queue.kinds import KINDS, covers
from precond.jobs.queue.payloads import Outcome
from precond.jobs.records import job_counts, record_phase, write_progress
from precond.worker import policies
from precond.worker.memory import MemoryGuard
from precond.worker.queue_worker import JobContext, JobEnd
from precond.worker.reinfer import keep as reinfer_keep
from precond.worker.reinfer import reinfer
from precond.worker.settings import WorkerSettings
from precond_client.schemas import ErrorInfo, JobKind, JobProgress
from precond_client.schemas.errors import PrecondError, ResourceLimit, ResponseTooLarge

ProgressFn = Callable[[str, int, int], None]
CancelledFn = Callable[[], bool]


@dataclass
class JobCounts:
    """The worker's own count of its runs, for its heartbeat: incremented when a run is taken (each try counts)
    and when it returns its outcome; never lower."""

    started: int = 0
    complete: int = 0


class ProgressReporter:
    """Engine progress → a Redis key the gateway reads, and per-phase wall time → the workers' stats hash.

    Called from the engine's thread, so writes are handed to the event loop and not awaited: progress is
    advisory and must never slow the engine down.
    """

    def __init__(
        self, redis: Redis[bytes], job_id: str, kind: JobKind, loop: asyncio.AbstractEventLoop, ttl_s: int
    ) -> None:
        self.redis, self.job_id, self.kind, self.loop, self.ttl_s = redis, job_id, kind, loop, ttl_s
        self.phase: str | None = None
        self.phase_started = time.perf_counter()
        self.reported = False
        """Whether the run wrote any progress (its end then reads the last back for the waiting processes)."""

    def __call__(self, phase: str, done: int, total: int) -> None:
        self.reported = True
        if phase != self.phase:
            self.finish_phase()
            self.phase, self.phase_started = phase, time.perf_counter()
        progress = JobProgress(phase=phase, done=done, total=total)
        self._submit(write_progress(self.redis, self.job_id, progress, self.ttl_s))

    def finish_phase(self) -> None:
        if self.phase is None:
            return
        self._submit(record_phase(self.redis, self.kind, self.phase, time.perf_counter() - self.phase_started))
        self.phase = None

    def _submit(self, coroutine: Any) -> None:
        asyncio.run_coroutine_threadsafe(coroutine, self.loop)


Keep = Callable[[Any, JobId, dict[str, Any], dict[str, Any]], Awaitable[Outcome]]


@dataclass(frozen=True)
class Runner:
    """What the worker does with one kind's payload: the engine's work (in the job's thread), then, on the event
    loop, what the kind keeps of a success (a set's next version, a trained policy: its outcome replaces the
    engine's) and what it leaves behind however the job ends (a training's scratch directory)."""

    run: Callable[[Engine, Any, ProgressFn, CancelledFn], BaseModel]
    keep: Keep | None = None
    discard: Callable[[dict[str, Any]], None] | None = None


RUNNERS: Final[dict[JobKind, Runner]] = {
    "infer": Runner(lambda engine, job, progress, cancelled: engine.infer(job, progress, cancelled)),
    "next-action": Runner(lambda engine, job, progress, cancelled: engine.next_action(job, progress, cancelled)),
    "check": Runner(lambda engine, job, _progress, _cancelled: engine.check(job, screened=True)),  # by the gateway
    "validate": Runner(lambda engine, job, _progress, _cancelled: engine.validate(
        job.spec, job.preconditions, job.demonstrations)),
    "reinfer": Runner(reinfer, keep=reinfer_keep),
    "train-policy": Runner(policies.train, keep=policies.keep, discard=policies.discard),
}
"""What the worker does with each kind's payload (`jobs.queue.kinds.KINDS` says which payload that is)."""
covers("precond/worker/jobs.py:RUNNERS", RUNNERS, KINDS)


def _operate(
    engine: Engine, kind: JobKind, body: dict[str, Any], progress: ProgressFn, cancelled: CancelledFn
) -> BaseModel:
    job = KINDS[kind].payload.model_validate(body)
    answer: BaseModel = RUNNERS[kind].run(engine, job, progress, cancelled)
    return answer


def _outcome(
    engine_of: Callable[[], Engine], kind: JobKind, body: dict[str, Any], progress: ProgressFn,
    cancelled: CancelledFn, max_response_bytes: int, scope: str, memory: Callable[[], AbstractContextManager[None]],
    warm: bool = True,
) -> tuple[Outcome, bool]:
    """A finished job's outcome, and whether a sandbox limit stopped it. A result larger than the bound is
    refused here, before Redis stores it twice (result and cache) and a client has to read it. The engine runs
    in the job's tenant's cache scope (precond/engine/scope.py): its model reuses only that tenant's prompt prefixes;
    `engine_of` is the served engine, or builds the one of the tenant's trained policy the job names. `warm`:
    whether the tenant's warm sandbox children may answer (never for a result shared between tenants, which must
    depend on its request alone)."""
    try:
        with memory(), scoped(scope, warm):
            result = _operate(engine_of(), kind, body, progress, cancelled).model_dump(mode="json")
    except PrecondError as exc:
        return Outcome.failed(exc), isinstance(exc, ResourceLimit)
    size = len(json.dumps(result))
    if size > max_response_bytes:
        message = (f"the answer would be {size:,} bytes, over PRECOND_MAX_RESPONSE_BYTES ({max_response_bytes:,}): "
                   "ask for fewer calls, actions or candidates")
        return Outcome(status="failed", error=ErrorInfo(type=ResponseTooLarge.kind, message=message)), False
    return Outcome(status="succeeded", result=result), False


@dataclass(frozen=True)
class Serving:
    """What this worker serves every job with: the engine, its settings, its counts, the result cache, the memory
    guard and the trained policies' engines."""

    engine: Engine
    settings: WorkerSettings
    counts: JobCounts
    cache: ResultCache
    memory: MemoryGuard
    adapted: policies.AdaptedEngines


async def run_operation(
    serving: Serving, context: JobContext, kind: JobKind, body: dict[str, Any], cache_key: str | None = None
) -> JobEnd:
    """The job function (`QueueWorker`'s, with `serving` bound). On cancellation (abort, timeout, shutdown) the
    engine is told and awaited to stop. The kind's runner keeps what a success makes and discards what it leaves
    behind. A success is cached under `cache_key` (the gateway's choice: the tenant's own or a shared entry), with
    the job's end (precond/worker/queue_worker.py); a shared one is computed on fresh sandbox children only."""
    job, runner = context.job, RUNNERS[kind]
    reporter = ProgressReporter(context.redis, job.value, kind, asyncio.get_running_loop(),
                                serving.settings.result_ttl_s)
    try:
        engine_of, body = await _engine_for(serving, context, kind, body)
        outcome, sandbox_limit = await _run(serving, context, reporter, kind, body, engine_of,
                                            warm=not is_shared(cache_key or ""))
        if runner.keep is not None and outcome.result is not None:
            outcome = await runner.keep(context.redis, job, body, outcome.result)
    except PrecondError as exc:
        outcome, sandbox_limit = Outcome.failed(exc), False
    finally:
        if runner.discard is not None:
            runner.discard(body)
    serving.counts.complete += 1
    # The cache lives in its own Redis (it may evict, or be down): a failed put only costs a later re-run.
    writes = () if outcome.result is None else (serving.cache.put(cache_key or job.value, outcome.result),)
    return JobEnd(outcome, job_counts(kind, outcome.status, sandbox_limit), writes, reporter.reported)


async def _engine_for(serving: Serving, context: JobContext, kind: JobKind, body: dict[str, Any]
                      ) -> tuple[Callable[[], Engine], dict[str, Any]]:
    """The engine a job runs on, and its body as it runs: a next action naming a trained policy runs on that
    policy's engine, read under the job owner's tenant (NotFound when it is not the owner's)."""
    engine = serving.engine
    policy = body.get("options", {}).get("policy") if kind == "next-action" else None
    if not policy:
        return (lambda: engine), body
    stored = await policies.fetch(context.redis, context.job.tenant, policy)
    return partial(serving.adapted.engine, engine, stored), policies.with_resolved_policy(body, stored)


async def _run(serving: Serving, context: JobContext, reporter: ProgressReporter, kind: JobKind,
               body: dict[str, Any], engine_of: Callable[[], Engine], warm: bool = True) -> tuple[Outcome, bool]:
    """The engine's work in a thread of the worker, under the job's memory bound and its tenant's cache scope,
    reporting its progress to `reporter`."""
    settings, job = serving.settings, context.job
    job_id = job.value
    loop = asyncio.get_running_loop()
    stop = threading.Event()
    future = loop.run_in_executor(
        None, _outcome, engine_of, kind, body, reporter, stop.is_set, settings.max_response_bytes,
        job.tenant, partial(serving.memory.running, job_id), warm,
    )
    try:
        return await asyncio.shield(future)
    except asyncio.CancelledError:
        stop.set()
        await asyncio.wait([future])
        raise
    finally:
        reporter.finish_phase()
