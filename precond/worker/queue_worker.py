"""The arq worker of one queue, with each job's start and end one Redis script on arq's own keys.

arq spends round trips on every job: one to read the queue, four to claim a job (WATCH, EXISTS, ZSCORE,
MULTI/EXEC), one to read it, one for the abort marks, one to record its end; around them this service added its
own (the claim under a fresh heartbeat, the queue-time and job counts, the result cache, the completion notice,
the claim's release). For a check that was seven round trips in a row on a job whose work takes a
millisecond. Here one script reads the abort marks and the queue and takes the next job (`_POLL`: arq's
in-progress key, its try count and abort mark, the job's bytes, and this service's claim with a fresh
heartbeat, atomically), and one ends it (`_FINISH`: arq's result and clean-up, the counts, the claim's release
and the notice with the end, atomically; the result cache, on its own Redis, at the same time). The keys and
values are arq's, so the gateway (status, cancel, abort) and the heartbeats' hand-back read them as before;
arq is pinned to the 0.28 series whose internals this subclasses.

What a job function hands back is a `JobEnd`: the outcome arq stores, the counts to add, and writes that go
with the end (the result cache).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import Counter
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Any, Protocol

from arq.constants import (
    abort_jobs_ss,
    in_progress_key_prefix,
    job_key_prefix,
    result_key_prefix,
    retry_key_prefix,
)
from arq.jobs import SerializationError, deserialize_job_raw, serialize_result
from arq.utils import ms_to_datetime, timestamp_ms, to_ms
from arq.worker import JobExecutionFailed, Worker
from redis.asyncio.client import PubSub
from redis.exceptions import RedisError

from precond.jobs.keys import (
    OWNER_SPAN_FROM_END,
    RUNNING_KEY,
    STATS_KEY,
    owner_of,
    progress_key,
    wake_channel,
    worker_key,
)
from precond.jobs.notices import NOTIFY_FUNCTION, RECORD_FUNCTION, RECORD_MAX_BYTES, waiters_key
from precond.jobs.records import queue_time_counts
from precond.jobs.scripts import LuaScript

log = logging.getLogger("precond.worker")
NOTICE_WAIT_S = 1.0
"""How long the new-job listener blocks per read of its connection (a notice ends the read at once, and so
does cancelling it): long, so that an idle listener costs no wake-ups."""
SAFETY_POLL_S = 1.0
"""How often a worker reads its queue while notices work (a notice can be lost, a job handed back)."""
RESUBSCRIBE_S = 1.0
"""Pause between attempts to subscribe to the wake channel again while its connection is down."""
RETRY_KEY_TTL_S = 88_400
"""arq's lifetime of a job's try count."""

_POLL = LuaScript("""
local aborts = redis.call('ZRANGE', KEYS[2], 0, -1)
if ARGV[13] ~= '1' then return {aborts} end
local skip = {}
for i = 14, #ARGV do skip[ARGV[i]] = true end
local queued = redis.call('ZRANGEBYSCORE', KEYS[1], '-inf', ARGV[1], 'WITHSCORES', 'LIMIT', 0, ARGV[6])
for n = 1, #queued, 2 do
  local id = queued[n]
  if not skip[string.sub(id, ARGV[11], ARGV[12])] and redis.call('EXISTS', ARGV[8] .. id) == 0 then
    redis.call('PSETEX', ARGV[8] .. id, ARGV[2], '1')
    local job = redis.call('GET', ARGV[9] .. id)
    local try = redis.call('INCR', ARGV[10] .. id)
    redis.call('EXPIRE', ARGV[10] .. id, ARGV[7])
    local aborted = redis.call('ZREM', KEYS[2], id)
    redis.call('SET', KEYS[3], ARGV[3], 'PX', ARGV[4])
    redis.call('HSET', KEYS[4], id, ARGV[5])
    return {aborts, id, queued[n + 1], job, try, aborted, #queued > 2 and 1 or 0}
  end
end
return {aborts}
""")
"""One poll of the queue: arq's abort marks (for the runs going on here), and, when this worker has a free
slot (ARGV[13]), the next job it may start, taken: the first of the queue's due jobs (in fair-score order, up
to the read limit) that no worker started (no in-progress key: none runs it, no cancellation guards it) and
whose tenant is not at its share here (its tag, read from the id's end, is not among those skipped). The take
sets arq's in-progress key and counts the try as arq's `start_jobs` and `run_job` do, and claims the job under
a fresh heartbeat (precond/jobs/heartbeats.py) in the same step, so no worker can die between the two and leave a
started job that no claim names. Returns the abort marks, then the job's id, score, bytes (false once
expired), try, whether an abort mark waited for it, and whether the read saw other jobs. Reading the queue and
the abort marks, choosing and claiming was six round trips in arq (eight with the claim), one here."""

_FINISH = LuaScript(NOTIFY_FUNCTION + RECORD_FUNCTION + """
if ARGV[2] == '1' then
  if ARGV[3] ~= '' then redis.call('SET', KEYS[1], ARGV[3], 'PX', ARGV[4]) end
  redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
  redis.call('ZREM', KEYS[5], ARGV[1])
  redis.call('ZREM', KEYS[6], ARGV[1])
else
  redis.call('DEL', KEYS[2])
end
for i = 7, #ARGV, 2 do redis.call('HINCRBYFLOAT', KEYS[8], ARGV[i], ARGV[i + 1]) end
if redis.call('HGET', KEYS[7], ARGV[1]) == ARGV[5] then redis.call('HDEL', KEYS[7], ARGV[1]) end
local result = false
if ARGV[2] == '1' and ARGV[3] ~= '' then result = ARGV[3] end
notify(KEYS[10], record(ARGV[1], redis.call('GET', KEYS[9]), result, ARGV[6]))
return redis.call('ZCARD', KEYS[6])
""")
"""End a run as arq's `finish_job` does: finished, its result stored and its keys gone; not finished (a
shutdown cancelled it), its in-progress key gone so that the job, still queued, runs again. With it, the
counts, this run's claim released (not a later run's), and the notice to the gateway processes that wait on the
job, carrying its end as stored (precond/jobs/notices.py). Returns how many jobs the queue holds now (queued, or running
elsewhere)."""


@dataclass(frozen=True)
class JobEnd:
    """What a job function returns to its worker: `stored`, the outcome arq keeps as the job's result; `counts`,
    stats to add (jobs/records.py); `writes`, what goes out with the end (the result cache, on its own Redis)."""

    stored: dict[str, Any]
    counts: dict[str, float] = field(default_factory=dict)
    writes: tuple[Awaitable[Any], ...] = ()


@dataclass(frozen=True)
class Claim:
    """This worker's claim on one run (`<worker id>|<nonce>`), and the heartbeat written with it."""

    worker: str
    token: str
    heartbeat: str
    lease_ms: int


class Claims(Protocol):
    """The worker process's record of the runs it claimed: its beats hand back the jobs of runs whose end, or
    whose take's answer, was lost (precond/worker/runner.py)."""

    worker_id: str

    def open(self) -> Claim: ...

    def taken(self, job_id: str, token: str) -> None: ...

    def lost(self, token: str) -> None: ...

    def close(self, job_id: str, token: str, recorded: bool) -> None: ...


@dataclass(frozen=True)
class Taken:
    id: str
    score: int
    job: bytes | None
    job_try: int
    aborted: bool


class TenantShareWorker(Worker):
    """An arq worker that runs at most `tenant_slots` jobs of one tenant at once, so the rest of its slots stay
    for the others, that is woken by the gateway's notice of a new job instead of waiting out its poll, and
    that takes and ends each job in one script (above).

    Fair scores (docs/tenants.md) decide who goes next, but reserve nothing: six checks that only wait (a
    history that sleeps) held all four check slots, and another tenant's check waited 15 s. arq starts every
    id it read, blocking for a free slot in between; here only as many ids as there are free slots are
    started, in score order, skipping tenants at their share (their jobs stay queued, for another worker or a
    later poll).

    arq sleeps `poll_delay` between reads of the queue, and for a check that sleep was most of its latency.
    Here the read runs again as soon as a gateway publishes on the queue's wake channel (a new job, an abort
    mark) or a slot frees up while jobs wait, and otherwise every `SAFETY_POLL_S` while the wake channel is
    subscribed, every `idle_poll_s` while it is not (then it is subscribed again every `RESUBSCRIBE_S`). Read
    every 10 ms as they were, the two fast queues cost an idle worker 9 % of a core beside the checks."""

    def __init__(self, *args: Any, tenant_slots: int, idle_poll_s: float, claims: Claims, **kwargs: Any) -> None:
        super().__init__(*args, poll_delay=0, **kwargs)
        self.tenant_slots = tenant_slots
        self.idle_poll_s = idle_poll_s
        self.claims = claims
        self._woken = asyncio.Event()
        self._listener: asyncio.Task[None] | None = None
        self.subscribed = False

    # ---------------------------------------------------------------------------------- choosing and taking

    async def _poll_iteration(self) -> None:
        """arq's poll, each read of the queue and the abort marks one script (`_POLL`), then done tasks and the
        health key, then a wait for a notice."""
        if self._listener is None:  # subscribe before the first read: a job enqueued before then is read below
            self._listener = asyncio.create_task(self._listen(await self._subscribe()))
        self._woken.clear()  # a notice that comes during the reads below makes the next poll start at once
        while await self._poll_once():
            pass
        for job_id, task in list(self.tasks.items()):
            if task.done():
                del self.tasks[job_id]
                task.result()  # an error of the run (Redis refused its end) ends this arq worker, as in arq
        await self.heart_beat()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._woken.wait(), SAFETY_POLL_S if self.subscribed else self.idle_poll_s)

    async def _poll_once(self) -> bool:
        """One `_POLL`: the abort marks acted on, and the next job taken and started when a slot is free.
        Whether to poll again at once (a job started, others were seen, a slot is still free). A take whose
        answer is lost may still have claimed a job: its claim is handed back by the next beat."""
        claim = self.claims.open() if self.allow_pick_jobs and self.job_counter < self.max_jobs else None
        if claim is not None:
            await self.sem.acquire()
            self.job_counter += 1
        try:
            aborts, taken, more = await self._poll_script(claim, self._at_share())
        except BaseException:
            if claim is not None:
                self.claims.lost(claim.token)
                self._release_sem_dec_counter_on_complete()
            raise
        await self._abort(aborts)
        if taken is None or claim is None:
            if claim is not None:
                self._release_sem_dec_counter_on_complete()
            return False
        self.claims.taken(taken.id, claim.token)
        task = self.loop.create_task(self._run(taken, claim))
        task.add_done_callback(self._slot_freed)
        self.tasks[taken.id] = task
        return more and self.job_counter < self.max_jobs

    def _at_share(self) -> list[str]:
        """The tenants with `tenant_slots` runs going on here."""
        running = Counter(owner_of(job_id) for job_id, task in self.tasks.items() if not task.done())
        return [tag for tag, count in running.items() if tag is not None and count >= self.tenant_slots]

    async def _poll_script(self, claim: Claim | None, at_share: list[str]
                           ) -> tuple[list[bytes], Taken | None, bool]:
        """`_POLL`, taking a job under `claim` (None: only the abort marks), skipping the tenants `at_share`."""
        heartbeat, lease_ms, token = (claim.heartbeat, claim.lease_ms, claim.token) if claim else ("", 0, "")
        answer = await _POLL(
            self.pool, [self.queue_name, abort_jobs_ss, worker_key(self.claims.worker_id), RUNNING_KEY],
            [timestamp_ms(), int(self.in_progress_timeout_s * 1000), heartbeat, lease_ms, token,
             self.queue_read_limit, RETRY_KEY_TTL_S, in_progress_key_prefix, job_key_prefix, retry_key_prefix,
             *OWNER_SPAN_FROM_END, "1" if claim else "0", *at_share],
        )
        if len(answer) == 1:
            return answer[0], None, False
        aborts, job_id, score, job, job_try, aborted, more = answer
        return aborts, Taken(job_id.decode(), int(float(score)), job or None, int(job_try), bool(aborted)), bool(more)

    async def _abort(self, marks: list[bytes]) -> None:
        """arq's `_cancel_aborted_jobs` on marks already read: the runs here that are marked are cancelled."""
        aborted = {mark.decode() for mark in marks} & set(self.job_tasks)
        for job_id in aborted:
            self.job_tasks[job_id].cancel()
        if aborted:
            self.aborting_tasks.update(aborted)
            await self.pool.zrem(abort_jobs_ss, *aborted)

    # ------------------------------------------------------------------------------------------ one run

    async def _run(self, taken: Taken, claim: Claim) -> bool:
        """arq's `run_job` after the take: the job's function under its timeout, then `_finish`. A run that
        cannot start (expired, unreadable, aborted before it started, out of tries) ends failed, as in arq.
        Returns whether other jobs wait in the queue."""
        start_ms, job_id = timestamp_ms(), taken.id
        job = _Job(job_id, taken, start_ms)
        refused = self._refusal(job)
        if refused is not None:
            self.jobs_failed += 1
            return await self._finish(job, claim, True, job.result(self, False, refused), JobEnd({}))
        function = self.functions[job.name]
        ctx = {**self.ctx, "job_id": job_id, "job_try": taken.job_try,
               "enqueue_time": ms_to_datetime(job.enqueue_ms), "score": taken.score, "claim": claim.token}
        waited = queue_time_counts(job_id, (start_ms - job.enqueue_ms) / 1000) if taken.job_try == 1 else {}
        timeout_s = self.job_timeout_s if function.timeout_s is None else function.timeout_s
        self.job_tasks[job_id] = task = self.loop.create_task(function.coroutine(ctx, *job.args, **job.kwargs))
        try:
            end: JobEnd = await asyncio.wait_for(task, timeout_s)
        except (Exception, asyncio.CancelledError) as exc:
            finished, error = self._failed(job_id, exc)
            return await self._finish(job, claim, finished, job.result(self, False, error) if finished else None,
                                      JobEnd({}, waited))
        finally:
            del self.job_tasks[job_id]
        self.jobs_complete += 1
        return await self._finish(job, claim, True, job.result(self, True, end.stored),
                                  JobEnd(end.stored, {**end.counts, **waited}, end.writes))

    def _refusal(self, job: _Job) -> BaseException | None:
        """Why a taken job must end without running, as arq would end it; None when it runs."""
        if job.taken.job is None:
            return JobExecutionFailed("job expired")
        try:
            job.read(self.job_deserializer)
        except SerializationError as exc:
            log.exception("deserializing job %s failed", job.id)
            return exc
        if job.taken.aborted:
            return asyncio.CancelledError()
        function = self.functions.get(job.name)
        if function is None:
            return JobExecutionFailed(f"function {job.name!r} not found")
        max_tries = self.max_tries if function.max_tries is None else function.max_tries
        if job.taken.job_try > max_tries:
            return JobExecutionFailed(f"max {max_tries} retries exceeded")
        return None

    def _failed(self, job_id: str, exc: BaseException) -> tuple[bool, BaseException]:
        """Whether a run that raised is finished: an abort or an error is the job's end; a cancellation
        otherwise (a shutdown) hands the job back to the queue, as in arq."""
        if job_id in self.aborting_tasks and isinstance(exc, asyncio.CancelledError):
            self.aborting_tasks.discard(job_id)
            self.jobs_failed += 1
            return True, exc
        if self.retry_jobs and isinstance(exc, asyncio.CancelledError):
            self.jobs_retried += 1
            return False, exc
        log.error("job %s failed: %r", job_id, exc, exc_info=exc)
        self.jobs_failed += 1
        return True, exc

    async def _finish(self, job: _Job, claim: Claim, finished: bool, stored: bytes | None, end: JobEnd) -> bool:
        """`_FINISH`, and the end's other writes at the same time (a shutdown must not cut them short).
        A Redis that refuses only the other writes costs a later re-run (a cache miss), never the job. Returns
        whether other jobs wait in the queue (a slot freed here may be exactly what one waits for)."""
        counts = [item for pair in end.counts.items() for item in pair]
        finish = _FINISH(
            self.pool,
            [result_key_prefix + job.id, in_progress_key_prefix + job.id, retry_key_prefix + job.id,
             job_key_prefix + job.id, abort_jobs_ss, self.queue_name, RUNNING_KEY, STATS_KEY, progress_key(job.id),
             waiters_key(job.id)],
            [job.id, "1" if finished else "0", stored or b"", to_ms(self.keep_result_s) or 0, claim.token,
             RECORD_MAX_BYTES, *counts],
        )
        # the other writes go out first: a client answered from the notice then finds its result cached
        *written, recorded = await _unstoppable(asyncio.gather(*end.writes, finish, return_exceptions=True))
        for outcome in written:
            if isinstance(outcome, BaseException) and not isinstance(outcome, RedisError | OSError):
                log.error("job %s: a write at its end failed: %r", job.id, outcome)
        if isinstance(recorded, BaseException):  # unrecorded: the claim's next beat hands the job back
            self.claims.close(job.id, claim.token, recorded=False)
            raise recorded
        self.claims.close(job.id, claim.token, recorded=True)
        return int(recorded) > 0

    def _slot_freed(self, task: asyncio.Task[bool]) -> None:
        self._release_sem_dec_counter_on_complete()
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
                    self.queue_name, exc, self.idle_poll_s)

    async def close(self) -> None:
        if self._listener is not None:
            self._listener.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._listener
        await super().close()


class _Job:
    """A taken job as its run reads it: arq's job bytes, decoded once."""

    def __init__(self, job_id: str, taken: Taken, start_ms: int) -> None:
        self.id, self.taken, self.start_ms = job_id, taken, start_ms
        self.name, self.enqueue_ms = "<unknown>", 0
        self.args: tuple[Any, ...] = ()
        self.kwargs: dict[str, Any] = {}

    def read(self, deserializer: Any) -> None:
        assert self.taken.job is not None
        self.name, self.args, self.kwargs, _, self.enqueue_ms = deserialize_job_raw(self.taken.job,
                                                                                   deserializer=deserializer)

    def result(self, worker: Worker, success: bool, result: Any) -> bytes | None:
        """arq's stored result of this run."""
        return serialize_result(self.name, self.args, self.kwargs, self.taken.job_try, self.enqueue_ms, success,
                                result, self.start_ms, timestamp_ms(), f"{self.id}:{self.name}",
                                worker.queue_name, self.id, serializer=worker.job_serializer)


async def _unstoppable(writes: asyncio.Future[list[Any]]) -> list[Any]:
    """The end's writes, awaited to their end: a shutdown cancels a run once when its drain ends and again when
    its worker closes, and a record cut short by the second would leave the run's claim to the next beat."""
    while True:
        try:
            return await asyncio.shield(writes)
        except asyncio.CancelledError:
            if writes.cancelled():
                raise
