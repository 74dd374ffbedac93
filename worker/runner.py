"""One worker process: arq workers for the model, model-free and check queues, model preload, heartbeats,
draining.

All queues run in one process so a single `precond worker` serves everything, yet check jobs and model-free
inferences never wait behind model jobs: each queue has its own arq worker with its own concurrency. A worker
survives Redis outages (it reconnects), and on SIGTERM stops taking jobs, lets running ones finish for `drain_s`, then
hands the rest back to the queue (arq re-queues a job cancelled by shutdown).

A SIGKILLed worker's jobs are handed back by the others: each job's claim in `precond:running` names the
worker running it, and every heartbeat tick of every live worker re-queues the jobs of workers whose
heartbeat has expired (jobs/heartbeats.py). A job this worker dropped itself (Redis went away while it
ran, so arq could not record its end) is handed back on the first beat after Redis returns.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import signal
import socket
import uuid
from collections import Counter
from datetime import UTC, datetime
from typing import Any

from arq import func
from arq.connections import RedisSettings
from arq.constants import in_progress_key_prefix
from arq.utils import timestamp_ms
from arq.worker import Worker
from redis.asyncio import Redis
from redis.asyncio.client import PubSub
from redis.exceptions import RedisError

from engine.engine import Engine
from engine.factory import build_engine
from jobs.cache import ResultCache
from jobs.heartbeats import Heartbeat, beat, claim, new_claim, release
from jobs.keys import (
    CHECK_QUEUE,
    JOB_FUNCTION,
    MODEL_QUEUE,
    MODEL_QUEUES,
    QUEUES,
    TRAIN_QUEUE,
    done_channel,
    kind_of,
    owner_of,
    wake_channel,
    worker_key,
)
from jobs.records import bookkeeping, record_queue_time
from sandbox import SandboxUnavailable
from worker import logs
from worker.jobs import JobCounts, run_operation
from worker.memory import MemoryGuard
from worker.policies import AdaptedEngines
from worker.settings import WorkerSettings, get_worker_settings

log = logging.getLogger("precond.worker")
NOTICE_WAIT_S = 1.0
"""How long the new-job listener blocks per read of its connection (a notice ends the read at once, and so
does cancelling it): long, so that an idle listener costs no wake-ups."""


_CLAIM = """
if redis.call('exists', KEYS[1]) == 1 then return false end
local score = redis.call('zscore', KEYS[2], ARGV[1])
if not score or tonumber(score) > tonumber(ARGV[2]) then return false end
redis.call('psetex', KEYS[1], ARGV[3], '1')
return score
"""
"""A queued job's claim, as arq makes it (its in-progress key, set unless it exists: another worker started it,
or a cancellation guards it), atomically: the job's score, or nil when it must not start here."""


class TenantShareWorker(Worker):
    """An arq worker that runs at most `tenant_slots` jobs of one tenant at once, so the rest of its slots stay
    for the others, and that is woken by the gateway's notice of a new job instead of waiting out its poll.

    Fair scores (docs/tenants.md) decide who goes next, but reserve nothing: six checks that only wait (a
    history that sleeps) held all four check slots, and another tenant's check waited 15 s. arq starts every
    id it read, blocking for a free slot in between; here only as many ids as there are free slots are
    started, in score order, skipping tenants at their share (their jobs stay queued, for another worker or a
    later poll).

    arq sleeps `poll_delay` between reads of the queue, and for a check that sleep was most of its latency.
    Here the read runs again as soon as a gateway publishes on the queue's wake channel or a slot frees up,
    and at the latest after `idle_poll_s` (a lost notice costs no more than arq's own poll). A job is claimed
    with one script (`_CLAIM`) rather than arq's four round trips."""

    def __init__(self, *args: Any, tenant_slots: int, idle_poll_s: float, **kwargs: Any) -> None:
        super().__init__(*args, poll_delay=0, **kwargs)
        self.tenant_slots = tenant_slots
        self.idle_poll_s = idle_poll_s
        self._woken = asyncio.Event()
        self._listener: asyncio.Task[None] | None = None

    async def start_jobs(self, job_ids: list[bytes]) -> None:
        running = Counter(owner_of(job_id) for job_id, task in self.tasks.items() if not task.done())
        chosen: list[str] = []
        for raw in job_ids:
            if len(chosen) >= self.max_jobs - self.job_counter:
                break
            job_id = raw.decode()
            tag = owner_of(job_id)
            if job_id not in self.tasks and running[tag] < self.tenant_slots:  # a started job stays queued
                running[tag] += 1
                chosen.append(job_id)
        for started in chosen:
            await self._start(started)

    async def _start(self, job_id: str) -> None:
        """arq's `start_jobs` for one id, with its claim in one script (`_CLAIM`) instead of WATCH, EXISTS,
        ZSCORE and MULTI/EXEC: four round trips on every job's latency, one here; the same keys and outcome."""
        await self.sem.acquire()
        if self.job_counter >= self.max_jobs:
            self.sem.release()
            return
        self.job_counter += 1
        score = await self.pool.eval(  # type: ignore[no-untyped-call]
            _CLAIM, 2, in_progress_key_prefix + job_id, self.queue_name, job_id, timestamp_ms(),
            int(self.in_progress_timeout_s * 1000),
        )
        if score is None:  # started elsewhere, finished, cancelled, or deferred again
            self.job_counter -= 1
            self.sem.release()
            return
        task = self.loop.create_task(self.run_job(job_id, int(float(score))))
        task.add_done_callback(lambda _: self._release_sem_dec_counter_on_complete())
        self.tasks[job_id] = task

    async def _poll_iteration(self) -> None:
        if self._listener is None:  # subscribe before the first read: a job enqueued before then is read below
            self._listener = asyncio.create_task(self._listen(await self._subscribe()))
        self._woken.clear()  # a notice that comes during the read below makes the next read start at once
        await super()._poll_iteration()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._woken.wait(), self.idle_poll_s)

    def _release_sem_dec_counter_on_complete(self) -> None:
        super()._release_sem_dec_counter_on_complete()
        self._woken.set()  # a slot is free: read the queue now, a job may be waiting for exactly that slot

    async def _subscribe(self) -> PubSub | None:
        pubsub = self.pool.pubsub()
        try:
            await pubsub.subscribe(wake_channel(self.queue_name))
        except (RedisError, OSError) as exc:
            self._lost(exc)
            return None
        return pubsub

    async def _listen(self, pubsub: PubSub | None) -> None:
        """Wake on the gateway's notices until the connection fails (then arq's pace, until the next worker)."""
        if pubsub is None:
            return
        try:
            while True:
                if await pubsub.get_message(ignore_subscribe_messages=True, timeout=NOTICE_WAIT_S) is not None:
                    self._woken.set()
        except (RedisError, OSError) as exc:
            self._lost(exc)
        finally:
            with contextlib.suppress(RedisError, OSError):
                await pubsub.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    def _lost(self, exc: Exception) -> None:
        log.warning("queue %s: new-job notices lost (%s); reading it every %ss", self.queue_name, exc,
                    self.idle_poll_s)

    async def close(self) -> None:
        if self._listener is not None:
            self._listener.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._listener
        await super().close()


class WorkerProcess:
    def __init__(self, settings: WorkerSettings, queues: list[str]) -> None:
        self.secret = settings.secret_bytes()  # MissingSecret: refuse to start, results could not be signed
        self.settings = settings
        self.queues = queues
        self.id = f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.engine: Engine | None = None
        self.sandbox, self.sandbox_error = "unavailable", None
        try:
            # A fork server per job slot: a job that waits in the sandbox (a history that sleeps) must hold only
            # its own slot's server, never one another tenant's job needs.
            self.engine = build_engine(with_model=bool(set(MODEL_QUEUES) & set(queues)),
                                       min_sandbox_workers=self.slots())
        except SandboxUnavailable as exc:  # fail closed: stay visible (heartbeat, /ready says why), take no job
            log.error("untrusted code cannot be confined here, so this worker takes no job: %s", exc)
            self.sandbox_error = str(exc)
        else:
            self.sandbox_error = self.engine.sandbox.unconfined_reason
            self.sandbox = "confined" if self.sandbox_error is None else "unconfined"
        self.workers: dict[str, Worker] = {}
        self.retired: list[Worker] = []  # arq workers ended by a Redis outage whose jobs may still be ending
        self.claims: dict[str, str] = {}  # job id → this worker's claim on it, while its run lasts
        self.dropped: dict[str, str] = {}  # claims of runs that ended unrecorded: to hand back at the next beat
        self.stopping = asyncio.Event()
        self.model_error: str | None = None
        self.counts = JobCounts()  # counted here, as jobs start and end, so they never go down
        self.cache: ResultCache | None = None  # on the cache Redis, opened in run()
        self.memory = MemoryGuard(settings.job_max_memory_mb * 1024 * 1024)
        self.policies = AdaptedEngines()

    def slots(self) -> int:
        """Jobs this process runs at once: check slots, a model slot and a model-free slot per concurrency, and
        one training."""
        return sum(map(self._concurrency, self.queues))

    def _concurrency(self, queue: str) -> int:
        s = self.settings
        if queue == CHECK_QUEUE:
            return s.check_concurrency
        return 1 if queue == TRAIN_QUEUE else s.worker_concurrency

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.drain, sig)
        redis = self._redis()
        cache_redis = redis if self.settings.cache_redis_dsn == self.settings.redis_dsn else self._redis(cache=True)
        self.cache = ResultCache(cache_redis, self.settings.cache_ttl_s, self.secret)
        with contextlib.suppress(RedisError, OSError):
            await self._beat(redis)  # be alive before claiming any job: a claim without a heartbeat is dead
        tasks: list[asyncio.Task[Any]] = (
            [asyncio.create_task(self.stopping.wait())] if self.engine is None
            else [asyncio.create_task(self._serve(queue, self.engine)) for queue in self.queues]
        )
        heartbeat = asyncio.create_task(self._heartbeat(redis))
        self.memory.start()
        gc.freeze()  # what start-up built lives as long as the process: the collector need not walk it again
        if self.engine is not None and self.settings.preload_model and MODEL_QUEUE in self.queues:
            tasks.append(asyncio.create_task(self._preload()))
        await asyncio.gather(*tasks)
        heartbeat.cancel()
        self.memory.stop()
        await self._forget(redis)
        if cache_redis is not redis:
            await cache_redis.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    def drain(self, sig: signal.Signals) -> None:
        log.info("%s: draining for up to %ss", sig.name, self.settings.drain_s)
        self.stopping.set()
        for worker in self.workers.values():
            worker.handle_sig_wait_for_completion(sig)

    def _arq_worker(self, queue: str, engine: Engine) -> Worker:
        s = self.settings
        model = queue in MODEL_QUEUES
        timeout = s.check_timeout_s if queue == CHECK_QUEUE else s.job_timeout_s
        max_jobs = self._concurrency(queue)
        return TenantShareWorker(
            functions=[func(run_operation, name=JOB_FUNCTION, timeout=timeout)],
            queue_name=queue,
            redis_settings=RedisSettings.from_dsn(s.redis_dsn),
            max_jobs=max_jobs,
            # Read twice the slots, so that a newcomer's job is seen behind a tenant at its share; only as many
            # as can start are started (TenantShareWorker), the rest stay queued in their fair order.
            queue_read_limit=2 * max_jobs,
            tenant_slots=s.tenant_slots(max_jobs),
            job_timeout=timeout,
            keep_result=s.result_ttl_s,
            max_tries=s.job_max_tries,
            idle_poll_s=s.worker_poll_s if model else s.check_poll_s,
            allow_abort_jobs=True,
            handle_signals=False,
            job_completion_wait=s.drain_s,
            health_check_interval=60,
            ctx={"engine": engine, "settings": s, "counts": self.counts, "cache": self.cache, "memory": self.memory,
                 "policies": self.policies},
            on_job_start=self._claim,
            after_job_end=self._job_ended,
        )

    async def _serve(self, queue: str, engine: Engine) -> None:
        """Run an arq worker on `queue` until drained, starting a new one after each Redis outage."""
        while not self.stopping.is_set():
            worker = self.workers[queue] = self._arq_worker(queue, engine)
            try:
                await worker.async_run()
            except asyncio.CancelledError:
                pass  # arq cancels its main task when a drain completes
            except (RedisError, OSError) as exc:
                log.warning("queue %s: redis unavailable (%s); reconnecting", queue, exc)
                self.retired.append(worker)  # its running jobs are cancelled by close(), unrecorded
                await asyncio.sleep(1)
            with contextlib.suppress(RedisError, OSError):
                await worker.close()

    async def _preload(self) -> None:
        assert self.engine is not None
        try:
            await asyncio.to_thread(self.engine.model)
        except Exception as exc:  # a broken model must not stop check jobs; the heartbeat reports it
            log.exception("model failed to load")
            self.model_error = f"{type(exc).__name__}: {exc}"
        gc.freeze()  # the model's modules and objects too (a full collection would walk them all again)

    def _heartbeat_body(self) -> Heartbeat:
        return Heartbeat(
            id=self.id,
            host=socket.gethostname(),
            pid=os.getpid(),
            queues=self.queues,
            model_loaded=self.engine is not None and self.engine.model_loaded,
            model_error=self.model_error,
            sandbox=self.sandbox,
            sandbox_error=self.sandbox_error,
            jobs_started=self.counts.started,
            jobs_complete=self.counts.complete,
        )

    async def _claim(self, ctx: dict[str, Any]) -> None:
        """arq's on_job_start (arq has set the job's in-progress key): claim the job under a fresh heartbeat.

        If Redis refuses, the job still runs: the next beat re-registers it.
        """
        self.counts.started += 1
        token = ctx["claim"] = self.claims[ctx["job_id"]] = new_claim(self.id)
        steps = [claim(ctx["redis"], self._heartbeat_body(), self.settings.heartbeat_lease_s, ctx["job_id"], token)]
        tag, kind = owner_of(ctx["job_id"]), kind_of(ctx["job_id"])
        if tag is not None and kind is not None and ctx.get("job_try", 1) == 1:
            waited = (datetime.now(UTC) - ctx["enqueue_time"]).total_seconds()
            steps.append(record_queue_time(ctx["redis"], tag, kind, max(0.0, waited)))
        await bookkeeping(steps)

    async def _job_ended(self, ctx: dict[str, Any]) -> None:
        """arq's after_job_end (arq has recorded the end: result stored, or the job re-queued)."""
        job_id, token = ctx["job_id"], ctx.get("claim")
        if token and self.claims.get(job_id) == token:
            del self.claims[job_id]
        await bookkeeping([_announce(ctx), *([release(ctx["redis"], job_id, token)] if token else [])])

    def _running(self) -> dict[str, str]:
        """Claims of the runs going on now; claims of runs that ended unrecorded move to `dropped`."""
        self.retired = [w for w in self.retired if any(not t.done() for t in w.tasks.values())]
        live = {
            job_id
            for worker in [*self.workers.values(), *self.retired]
            for job_id, task in worker.tasks.items()
            if not task.done()
        }
        for job_id in [j for j in self.claims if j not in live]:
            self.dropped[job_id] = self.claims.pop(job_id)
        return dict(self.claims)

    async def _beat(self, redis: Redis[bytes]) -> None:
        running, dropped = self._running(), dict(self.dropped)
        released = await beat(
            redis, self._heartbeat_body(), self.settings.heartbeat_lease_s, running=running, dropped=dropped
        )
        for job_id, token in dropped.items():
            if self.dropped.get(job_id) == token:
                del self.dropped[job_id]
        if released:
            log.warning("handed back to the queue (their run is gone): %s", ", ".join(released))

    async def _heartbeat(self, redis: Redis[bytes]) -> None:
        while True:
            await asyncio.sleep(self.settings.heartbeat_s)
            try:
                await self._beat(redis)
            except (RedisError, OSError):
                pass
            except Exception:  # a heartbeat that stops makes this worker look dead: log, keep beating
                log.exception("heartbeat failed")

    async def _forget(self, redis: Redis[bytes]) -> None:
        with contextlib.suppress(RedisError, OSError):
            await redis.delete(worker_key(self.id))
        await redis.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    def _redis(self, cache: bool = False) -> Redis[bytes]:
        dsn = self.settings.cache_redis_dsn if cache else self.settings.redis_dsn
        return Redis.from_url(dsn, socket_connect_timeout=2, socket_timeout=5)


async def _announce(ctx: dict[str, Any]) -> None:
    """Tell waiting gateways that the job's result is stored (arq calls this after recording it).

    Advisory: a lost message only delays a waiter until its next fallback poll.
    """
    await ctx["redis"].publish(done_channel(ctx["job_id"]), b"1")


def run(settings: WorkerSettings, queues: list[str] | None = None) -> None:
    logs.configure()
    asyncio.run(WorkerProcess(settings, queues or list(QUEUES)).run())


if __name__ == "__main__":
    run(get_worker_settings())
