"""One worker process: a queue worker each for the model, model-free, check and training queues, model preload,
heartbeats, draining.

All queues run in one process so a single `precond worker` serves everything, yet check jobs and model-free
inferences never wait behind model jobs: each queue has its own worker with its own concurrency. A worker
survives Redis outages (it reconnects), and on SIGTERM stops taking jobs, lets running ones finish for `drain_s`, then
hands the rest back to the queue (a run cancelled by a shutdown leaves its job queued).

A SIGKILLed worker's jobs are handed back by the others: each job's claim in `precond:running` names the
worker running it, and every heartbeat tick of every live worker re-queues the jobs of workers whose
heartbeat has expired (precond/jobs/queue/heartbeats.py). A job this worker dropped itself (Redis went away while it
ran, so its end could not be recorded) is handed back on the first beat after Redis returns.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import signal
import socket
import threading
import uuid
from collections.abc import Callable
from functools import partial
from typing import Any

import uvloop
from redis.asyncio import Redis
from redis.exceptions import RedisError

from precond.engine.engine import Engine
from precond.engine.factory import build_engine
from precond.jobs.cache import ResultCache
from precond.jobs.queue.heartbeats import Heartbeat, beat, new_claim
from precond.jobs.queue.keys import (
    CHECK_QUEUE,
    MODEL_QUEUE,
    MODEL_QUEUES,
    QUEUES,
    TRAIN_QUEUE,
    wake_channel,
    worker_key,
)
from precond.jobs.queue.steps import Claim
from precond.jobs.records import PendingCounts, write_counts
from precond.patches.redis_checkout import check_out_without_read
from precond.patches.redis_packing import pack_with_hiredis
from precond.patches.redis_sending import send_without_task
from precond.sandbox import SandboxUnavailable
from precond.worker import logs
from precond.worker.jobs import JobCounts, Serving, run_operation
from precond.worker.memory import MemoryGuard
from precond.worker.policies import AdaptedEngines
from precond.worker.queue_worker import QueueWorker, RunSettings
from precond.worker.settings import WorkerSettings, get_worker_settings

log = logging.getLogger("precond.worker")


class RunClaims:
    """This process's claims on the runs it takes (`live`: job id → claim, while the run lasts), and the claims
    that may be in Redis without their run's end (`dropped`: the end, or the take's answer, was lost), whose
    jobs the next beat hands back."""

    def __init__(self, worker_id: str, heartbeat: Callable[[], Heartbeat], lease_s: float,
                 counts: JobCounts | None = None) -> None:
        self.worker_id, self.heartbeat, self.lease_ms = worker_id, heartbeat, int(lease_s * 1000)
        self.counts = counts or JobCounts()
        self.live: dict[str, str] = {}
        self.dropped: set[str] = set()

    def open(self) -> Claim:
        """A claim for the next take, with the heartbeat the take writes (counting the run it would start)."""
        heartbeat = self.heartbeat()
        heartbeat.jobs_started += 1
        return Claim(self.worker_id, new_claim(self.worker_id), heartbeat.model_dump_json(), self.lease_ms)

    def taken(self, job_id: str, token: str) -> None:
        """A run started: every take counts, as arq counts each as a try."""
        self.counts.started += 1
        self.live[job_id] = token

    def lost(self, token: str) -> None:
        """A take whose answer never came: its script may have claimed a job this process never learned."""
        self.dropped.add(token)

    def close(self, job_id: str, token: str, recorded: bool) -> None:
        """Forget a run's claim; one whose end went unrecorded is kept for the next beat to hand back."""
        if self.live.get(job_id) == token:
            del self.live[job_id]
            if not recorded:
                self.dropped.add(token)


class WorkerProcess:
    def __init__(self, settings: WorkerSettings, queues: list[str]) -> None:
        self.secret = settings.secret_bytes()  # MissingSecret: refuse to start, results could not be signed
        self.settings = settings
        self.queues = queues
        self.host, self.pid = socket.gethostname(), os.getpid()  # read once: every take writes a heartbeat
        self.id = f"{self.host}-{self.pid}-{uuid.uuid4().hex[:6]}"
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
        self.workers: dict[str, QueueWorker] = {}
        self.retired: list[QueueWorker] = []  # workers ended by a Redis outage whose jobs may still be ending
        self.counts = JobCounts()  # counted here, as jobs start and end, so they never go down
        self.stats = PendingCounts()  # the runs' stats, written by the next beat
        self.claims = RunClaims(self.id, self._heartbeat_body, settings.heartbeat_lease_s, self.counts)
        self.stopping = asyncio.Event()
        self.model_error: str | None = None
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
        log.info("worker %s started: queues %s, sandbox %s", self.id, ", ".join(self.queues), self.sandbox)
        self.memory.start()
        gc.freeze()  # what start-up built lives as long as the process: the collector need not walk it again
        if self.engine is not None and self.settings.preload_model and MODEL_QUEUE in self.queues:
            # a daemon thread, never awaited: a SIGTERM while the model loads stops the worker within its drain,
            # not after the load (which cannot be interrupted: tens of seconds for a model read from disk)
            threading.Thread(target=self._preload, args=(self.engine,), name="model-preload", daemon=True).start()
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
            worker.drain()

    def _queue_worker(self, queue: str, engine: Engine) -> QueueWorker:
        s = self.settings
        max_jobs = self._concurrency(queue)
        settings = RunSettings(
            queue=queue,
            max_jobs=max_jobs,
            tenant_slots=s.tenant_slots(max_jobs),
            timeout_s=s.check_timeout_s if queue == CHECK_QUEUE else s.job_timeout_s,
            keep_result_s=s.result_ttl_s,
            max_tries=s.job_max_tries,
            idle_poll_s=s.worker_poll_s if queue in MODEL_QUEUES else s.check_poll_s,
            drain_s=s.drain_s,
        )
        assert self.cache is not None, "the cache is opened in run(), before any queue is served"
        serving = Serving(engine, s, self.counts, self.cache, self.memory, self.policies)
        return QueueWorker(partial(run_operation, serving), settings, s.redis_dsn, self.claims, self.stats)

    async def _serve(self, queue: str, engine: Engine) -> None:
        """Run a queue worker on `queue` until drained, starting a new one after each Redis outage."""
        while not self.stopping.is_set():
            worker = self.workers[queue] = self._queue_worker(queue, engine)
            try:
                await worker.run()
            except (RedisError, OSError) as exc:
                log.warning("queue %s: redis unavailable (%s); reconnecting", queue, exc)
                self.retired.append(worker)  # its running jobs are cancelled by close(), unrecorded
                await asyncio.sleep(1)
            with contextlib.suppress(RedisError, OSError):
                await worker.close()

    def _preload(self, engine: Engine) -> None:
        try:
            engine.model()
        except Exception as exc:  # a broken model must not stop check jobs; the heartbeat reports it
            log.exception("model failed to load")
            self.model_error = f"{type(exc).__name__}: {exc}"
        gc.freeze()  # the model's modules and objects too (a full collection would walk them all again)

    def _heartbeat_body(self) -> Heartbeat:
        return Heartbeat.model_construct(  # this process's own values: nothing to validate
            id=self.id,
            host=self.host,
            pid=self.pid,
            queues=self.queues,
            model_loaded=self.engine is not None and self.engine.model_loaded,
            model_error=self.model_error,
            sandbox=self.sandbox,
            sandbox_error=self.sandbox_error,
            jobs_started=self.counts.started,
            jobs_complete=self.counts.complete,
        )

    def _running(self) -> dict[str, str]:
        """Claims of the runs going on now; claims of runs that ended unrecorded move to `dropped`."""
        self.retired = [w for w in self.retired if any(not t.done() for t in w.tasks.values())]
        live = {
            job_id
            for worker in [*self.workers.values(), *self.retired]
            for job_id, task in worker.tasks.items()
            if not task.done()
        }
        for job_id in [j for j in self.claims.live if j not in live]:
            self.claims.dropped.add(self.claims.live.pop(job_id))
        return dict(self.claims.live)

    async def _beat(self, redis: Redis[bytes]) -> None:
        running, dropped, counts = self._running(), set(self.claims.dropped), self.stats.take()
        try:
            released = await beat(redis, self._heartbeat_body(), self.settings.heartbeat_lease_s, running=running,
                                  dropped=dropped, counts=counts)
        except BaseException:
            self.stats.add(counts)  # for the next beat
            raise
        self.claims.dropped -= dropped
        if released:
            log.warning("handed back to the queue (their run is gone): %s", ", ".join(released))
            async with redis.pipeline(transaction=False) as pipe:  # a worker reads its queue at once
                for queue in QUEUES:
                    pipe.publish(wake_channel(queue), b"1")
                await pipe.execute()

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
        """The last runs' counts written, and this worker's heartbeat gone."""
        with contextlib.suppress(RedisError, OSError):
            await write_counts(redis, self.stats.take())
            await redis.delete(worker_key(self.id))
        await redis.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    def _redis(self, cache: bool = False) -> Redis[bytes]:
        dsn = self.settings.cache_redis_dsn if cache else self.settings.redis_dsn
        return Redis.from_url(dsn, socket_connect_timeout=2, socket_timeout=5)


def run(settings: WorkerSettings) -> None:
    logs.configure()
    pack_with_hiredis()
    check_out_without_read()
    send_without_task()
    uvloop.run(WorkerProcess(settings, settings.queues).run())


if __name__ == "__main__":
    run(get_worker_settings())
