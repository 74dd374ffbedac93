"""The worker of one queue: a loop that takes each job and ends it with one script each
(`precond.jobs.queue.steps`), runs at most `tenant_slots` jobs of one tenant at once, and is woken by the
gateway's notice of a new job instead of waiting out its poll.

The project owns its queue (`precond.jobs.queue`): this loop is the queue's only consumer, and calls no
queue library's worker. What a job function hands back is a `JobEnd`: the outcome stored as the job's end, the
counts to add, and writes that go with the end (the result cache).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any, Protocol

from redis.asyncio import Redis
from redis.asyncio.client import PubSub
from redis.exceptions import RedisError

from precond.jobs.queue import steps
from precond.jobs.queue.keys import JobId, wake_channel
from precond.jobs.queue.payloads import (
    MAX_REASON_CHARS,
    RECORD_VERSION,
    EndRecord,
    Failure,
    JobRecord,
    Outcome,
    RecordError,
    decode_job,
    encode_end,
)
from precond.jobs.queue.steps import Claim, Taken
from precond.jobs.records import PendingCounts, queue_time_counts
from precond_client.schemas import JobKind

log = logging.getLogger("precond.worker")
NOTICE_WAIT_S = 1.0
"""How long the new-job listener blocks per read of its connection (a notice ends the read at once, and so
does cancelling it): long, so that an idle listener costs no wake-ups."""
SAFETY_POLL_S = 1.0
"""How often a worker reads its queue while notices work (a notice can be lost, a job handed back)."""
RESUBSCRIBE_S = 1.0
"""Pause between attempts to subscribe to the wake channel again while its connection is down."""
IN_PROGRESS_EXTRA_S = 10
"""How much longer than the job timeout a run's in-progress mark lasts (the heartbeats hand back dead runs)."""


@dataclass(frozen=True)
class JobEnd:
    """What a job function returns to its worker: `outcome`, stored as the job's end (None for a run that
    returned none); `counts`, stats to add (jobs/records.py); `writes`, what goes out with the end (the result
    cache, on its own Redis); `progressed`, whether the run may have written progress (a run that never did, a
    check, spares its end the read of the progress key)."""

    outcome: Outcome | None = None
    counts: dict[str, float] = field(default_factory=dict)
    writes: tuple[Awaitable[Any], ...] = ()
    progressed: bool = True


class Claims(Protocol):
    """The worker process's record of the runs it claimed: its beats hand back the jobs of runs whose end, or
    whose take's answer, was lost (precond/worker/runner.py)."""

    worker_id: str

    def open(self) -> Claim: ...

    def taken(self, job_id: str, token: str) -> None: ...

    def lost(self, token: str) -> None: ...

    def close(self, job_id: str, token: str, recorded: bool) -> None: ...


@dataclass(frozen=True)
class JobContext:
    """What a job function is handed besides its record: the queue Redis of its worker, and the job's identity
    (its id and tenant). What the worker serves jobs with (the engine, the cache, ...) the job function holds."""

    redis: Redis[bytes]
    job: JobId


Operation = Callable[[JobContext, JobKind, dict[str, Any], str | None], Coroutine[Any, Any, JobEnd]]
"""The job function: `(context, kind, body, cache_key)` of a job's record."""


@dataclass(frozen=True)
class RunSettings:
    """How one queue's worker runs its jobs."""

    queue: str
    max_jobs: int
    """Jobs run at once."""
    tenant_slots: int
    """Jobs of one tenant run at once (at most `max_jobs`)."""
    timeout_s: float
    keep_result_s: float
    max_tries: int
    idle_poll_s: float
    """How often the queue is read while its wake channel is not subscribed."""
    drain_s: float = 0.0
    """How long a drain lets running jobs finish before it cancels them (they go back to the queue)."""
    read_limit: int | None = None
    """Due jobs read per take; twice the slots by default, so that a newcomer's job is seen behind a tenant at its
    share (only as many as can start are started, the rest stay queued in their fair order)."""


class QueueWorker:
    """Runs the jobs of one queue, at most `tenant_slots` of one tenant at once, so the rest of its slots stay
    for the others.

    Fair scores (docs/tenants.md) decide who goes next, but reserve nothing: six checks that only wait (a
    history that sleeps) held all four check slots, and another tenant's check waited 15 s. Here only as many
    jobs as there are free slots are taken, in score order, skipping tenants at their share (their jobs stay
    queued, for another worker or a later poll).

    A poll's sleep was most of a check's latency. Here the queue is read again as soon as a gateway publishes on
    the queue's wake channel (a new job, an abort mark) or a slot frees up while jobs wait, and otherwise every
    `SAFETY_POLL_S` while the wake channel is subscribed, every `idle_poll_s` while it is not (then it is
    subscribed again every `RESUBSCRIBE_S`). Read every 10 ms as they were, the two fast queues cost an idle
    worker 9 % of a core beside the checks.

    `run` returns once a drain (`drain`) or a stop (`stop`) ends it, and raises the Redis error that ends it
    otherwise (the worker process then starts another, precond/worker/runner.py); `close` waits for the ends of
    the runs it cancelled and closes its connections. The counts of the runs whose end it recorded go to `stats`,
    which the worker process's heartbeat writes."""

    def __init__(self, operation: Operation, settings: RunSettings, redis_url: str, claims: Claims,
                 stats: PendingCounts) -> None:
        self.operation, self.settings, self.claims, self.stats = operation, settings, claims, stats
        self.queue_name = settings.queue
        self.pool: Redis[bytes] = Redis.from_url(redis_url, socket_connect_timeout=1)
        self.how = steps.Take(settings.queue, claims.worker_id, settings.read_limit or 2 * settings.max_jobs,
                              int((settings.timeout_s + IN_PROGRESS_EXTRA_S) * 1000))
        self.tasks: dict[str, asyncio.Task[bool]] = {}
        """The runs going on (each one's take to its recorded end), by job id."""
        self.job_tasks: dict[str, asyncio.Task[JobEnd]] = {}
        """The job functions running, by job id (what an abort cancels)."""
        self.aborting: set[str] = set()
        self.busy = 0
        self.picking = True
        self.subscribed = False
        self._woken = asyncio.Event()
        self._stopped = asyncio.Event()
        self._listener: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------------------------------ the loop

    async def run(self) -> None:
        """Poll until stopped: each poll takes jobs while slots are free, then waits for a notice."""
        self._listener = asyncio.create_task(self._listen(await self._subscribe()))  # before the first read
        while not self._stopped.is_set():
            self._woken.clear()  # a notice that comes during the reads below makes the next poll start at once
            while not self._stopped.is_set() and await self._poll_once():
                pass
            for job_id, task in list(self.tasks.items()):
                if task.done():
                    del self.tasks[job_id]
                    task.result()  # an error of the run (Redis refused its end) ends this worker
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._woken.wait(), SAFETY_POLL_S if self.subscribed else
                                       self.settings.idle_poll_s)

    def drain(self) -> None:
        """Take no more jobs; let the running ones finish for `drain_s`, then cancel them (back to the queue)."""
        self.picking = False
        self._drain = asyncio.get_running_loop().create_task(self._finish_then_stop())

    async def _finish_then_stop(self) -> None:
        deadline = time.monotonic() + self.settings.drain_s
        while any(not t.done() for t in self.tasks.values()) and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        self.stop()

    def stop(self) -> None:
        """Cancel the running jobs (each goes back to its queue) and end `run`."""
        self.picking = False
        for task in self.job_tasks.values():
            task.cancel()
        self._stopped.set()
        self._woken.set()

    async def close(self) -> None:
        """Stop, wait for the cancelled runs' ends to be recorded, and close the connections."""
        self.stop()
        await asyncio.gather(*self.tasks.values(), return_exceptions=True)
        if self._listener is not None:
            self._listener.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._listener
        await self.pool.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    # ---------------------------------------------------------------------------------- choosing and taking

    async def _poll_once(self) -> bool:
        """One take: the abort marks acted on, and the next job taken and started when a slot is free.
        Whether to poll again at once (a job started, others were seen, a slot is still free). A take whose
        answer is lost may still have claimed a job: its claim is handed back by the next beat."""
        claim = self.claims.open() if self.picking and self.busy < self.settings.max_jobs else None
        if claim is not None:
            self.busy += 1
        try:
            aborts, taken, more = await steps.take(self.pool, self.how, int(time.time() * 1000), claim,
                                                   self._at_share())
        except BaseException:
            if claim is not None:
                self.claims.lost(claim.token)
                self.busy -= 1
            raise
        await self._abort(aborts)
        if taken is None or claim is None:
            if claim is not None:
                self.busy -= 1
            return False
        self.claims.taken(taken.id, claim.token)
        task = asyncio.get_running_loop().create_task(self._run(taken, claim))
        task.add_done_callback(self._slot_freed)
        self.tasks[taken.id] = task
        return more and self.busy < self.settings.max_jobs

    def _at_share(self) -> list[str]:
        """The tenants with `tenant_slots` runs going on here."""
        running = [JobId.read(job_id) for job_id, task in self.tasks.items() if not task.done()]
        tenants = Counter(job.tenant for job in running if job is not None)
        return [tag for tag, count in tenants.items() if count >= self.settings.tenant_slots]

    async def _abort(self, marks: list[bytes]) -> None:
        """The runs here that are marked for abort are cancelled, and their marks forgotten."""
        aborted = {mark.decode() for mark in marks} & set(self.job_tasks)
        for job_id in aborted:
            self.job_tasks[job_id].cancel()
        self.aborting.update(aborted)
        await steps.clear_aborts(self.pool, aborted)

    # ------------------------------------------------------------------------------------------ one run

    async def _run(self, taken: Taken, claim: Claim) -> bool:
        """The job's function under its timeout, then `_finish`. A run that cannot start (expired, unreadable,
        aborted before it started, out of tries) ends failed. Returns whether other jobs wait in the queue."""
        job = _Job(taken.id, taken, int(time.time() * 1000))
        refused = self._refusal(job)
        if refused is not None or job.identity is None or job.record is None:
            return await self._finish(job, claim, True, job.end(self.queue_name, refused), JobEnd())
        record, job_id = job.record, job.id
        context = JobContext(self.pool, job.identity)
        waited = queue_time_counts(job.identity, (job.start_ms - record.enqueued_ms) / 1000) \
            if taken.job_try == 1 else {}
        self.job_tasks[job_id] = task = asyncio.get_running_loop().create_task(
            self.operation(context, record.kind, record.body, record.cache_key))
        try:
            end: JobEnd = await asyncio.wait_for(task, self.settings.timeout_s)
        except (Exception, asyncio.CancelledError) as exc:
            finished = self._finished(job_id, exc)
            return await self._finish(job, claim, finished, job.end(self.queue_name, _failure(exc)) if finished
                                      else None, JobEnd(None, waited))
        finally:
            del self.job_tasks[job_id]
        return await self._finish(job, claim, True, job.end(self.queue_name, end.outcome),
                                  JobEnd(end.outcome, {**end.counts, **waited}, end.writes, end.progressed))

    def _refusal(self, job: _Job) -> Failure | None:
        """Why a taken job must end without running; None when it runs. A record that fails its schema (or is
        of another version) is refused unread: nothing in it runs."""
        if job.identity is None:
            return _refused(f"not a job id of this service: {job.id[:120]!r}")
        if job.taken.job is None:
            return _refused("job expired")
        try:
            job.read()
        except RecordError as exc:
            log.error("job %s: its record is refused: %s", job.id, exc)
            return _refused(f"the job's record is refused: {exc}")
        if job.taken.aborted:
            return Failure(reason="cancelled", message="the job was cancelled")
        if job.taken.job_try > self.settings.max_tries:
            return Failure(reason="retries_exceeded", message=f"max {self.settings.max_tries} retries exceeded")
        return None

    def _finished(self, job_id: str, exc: BaseException) -> bool:
        """Whether a run that raised is finished: an abort or an error is the job's end; a cancellation
        otherwise (a drain, a stop) hands the job back to the queue."""
        if job_id in self.aborting and isinstance(exc, asyncio.CancelledError):
            self.aborting.discard(job_id)
            return True
        if isinstance(exc, asyncio.CancelledError):
            return False
        log.error("job %s failed: %r", job_id, exc, exc_info=exc)
        return True

    async def _finish(self, job: _Job, claim: Claim, finished: bool, stored: bytes | None, end: JobEnd) -> bool:
        """`steps.finish`, and the end's other writes at the same time (a shutdown must not cut them short).
        A Redis that refuses only the other writes costs a later re-run (a cache miss), never the job. Returns
        whether other jobs wait in the queue (a slot freed here may be exactly what one waits for)."""
        finish = steps.finish(self.pool, steps.Finish(
            self.queue_name, job.id, claim.token, finished, stored, int(self.settings.keep_result_s * 1000),
            end.progressed))
        # the other writes go out first: a client answered from the notice then finds its result cached
        *written, recorded = await _unstoppable(asyncio.gather(*end.writes, finish, return_exceptions=True))
        for outcome in written:
            if isinstance(outcome, BaseException) and not isinstance(outcome, RedisError | OSError):
                log.error("job %s: a write at its end failed: %r", job.id, outcome)
        if isinstance(recorded, BaseException):  # unrecorded: the claim's next beat hands the job back
            self.claims.close(job.id, claim.token, recorded=False)
            raise recorded
        self.claims.close(job.id, claim.token, recorded=True)
        self.stats.add(end.counts)
        return int(recorded) > 0

    def _slot_freed(self, task: asyncio.Task[bool]) -> None:
        self.busy -= 1
        if task.cancelled() or task.exception() is not None or task.result():
            self._woken.set()  # read the queue now: a job may be waiting for exactly this slot

    # --------------------------------------------------------------------------------------- wake-ups

    async def _subscribe(self) -> PubSub | None:
        pubsub = self.pool.pubsub()
        try:
            await pubsub.subscribe(wake_channel(self.queue_name))
        except (RedisError, OSError) as exc:
            self._lost(exc)
            with contextlib.suppress(RedisError, OSError):
                await pubsub.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose
            return None
        self.subscribed = True
        return pubsub

    async def _listen(self, pubsub: PubSub | None) -> None:
        """Wake on the gateway's notices; when the subscription fails, subscribe again every `RESUBSCRIBE_S`
        (polling at `idle_poll_s` meanwhile), and read the queue once it is back."""
        while True:
            if pubsub is not None:
                try:
                    while True:
                        if await pubsub.get_message(ignore_subscribe_messages=True, timeout=NOTICE_WAIT_S):
                            self._woken.set()
                except (RedisError, OSError) as exc:
                    self._lost(exc)
                finally:
                    self.subscribed = False
                    with contextlib.suppress(RedisError, OSError):
                        await pubsub.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose
            await asyncio.sleep(RESUBSCRIBE_S)
            pubsub = await self._subscribe()
            self._woken.set()  # a notice may have been missed meanwhile

    def _lost(self, exc: Exception) -> None:
        log.warning("queue %s: new-job notices lost (%s); reading it every %ss until they are back",
                    self.queue_name, exc, self.settings.idle_poll_s)


class _Job:
    """A taken job as its run reads it: its record, decoded once."""

    def __init__(self, job_id: str, taken: Taken, start_ms: int) -> None:
        self.id, self.taken, self.start_ms = job_id, taken, start_ms
        self.identity = JobId.read(job_id)
        """The job's kind and tenant, read once here; None for an id this service never hands out."""
        self.record: JobRecord | None = None

    def read(self) -> None:
        """The job's record; RecordError for bytes that are not one, or one of another kind than its id's
        (its queue, its tenant's bounds and its cache scope were chosen by the id)."""
        assert self.taken.job is not None and self.identity is not None
        record = decode_job(self.taken.job)
        if record.kind != self.identity.kind:
            raise RecordError(f"a {record.kind!r} record under a {self.identity.kind!r} job id")
        self.record = record

    def end(self, queue: str, how: Outcome | Failure | None) -> bytes:
        """The stored end of this run: the outcome it returned, or why it ended without one (built unvalidated:
        every part is a model already, and the gateway validates what it reads)."""
        outcome, failure = (how, None) if isinstance(how, Outcome) else (None, how)
        return encode_end(EndRecord.model_construct(
            version=RECORD_VERSION, job_id=self.id[:200], queue=queue, job_try=self.taken.job_try,
            enqueued_ms=self.record.enqueued_ms if self.record else 0, start_ms=self.start_ms,
            finish_ms=int(time.time() * 1000), outcome=outcome, failure=failure))


def _refused(message: str) -> Failure:
    return Failure(reason="refused", message=message[:MAX_REASON_CHARS])


def _failure(exc: BaseException) -> Failure:
    """How a run that raised ended: cancelled by an abort, or crashed (its error, a timeout)."""
    if isinstance(exc, asyncio.CancelledError):
        return Failure(reason="cancelled", message="the job was cancelled")
    return Failure(reason="crashed", message=repr(exc)[:MAX_REASON_CHARS])


async def _unstoppable(writes: asyncio.Future[list[Any]]) -> list[Any]:
    """The end's writes, awaited to their end: a shutdown cancels a run once when its drain ends and again when
    its worker closes, and a record cut short by the second would leave the run's claim to the next beat."""
    while True:
        try:
            return await asyncio.shield(writes)
        except asyncio.CancelledError:
            if writes.cancelled():
                raise
