"""The arq job: run one engine operation in a thread, report its progress, cache its result.

The engine is CPU-bound and synchronous; running it in a thread keeps the worker's event loop free for
arq's polling, abort checks and the heartbeat. Cancellation crosses the thread boundary as a predicate the
engine polls between steps.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from collections.abc import Callable
from typing import Any

from pydantic import BaseModel
from redis.asyncio import Redis
from redis.exceptions import RedisError

from engine.engine import Engine
from schemas.api import CheckRequest, InferRequest, JobKind, NextActionRequest
from schemas.errors import PrecondError, ResourceLimit
from service.cache import ResultCache
from service.keys import STATS_KEY, progress_key
from service.settings import Settings

ProgressFn = Callable[[str, int, int], None]
CancelledFn = Callable[[], bool]


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

    def __call__(self, phase: str, done: int, total: int) -> None:
        if phase != self.phase:
            self.finish_phase()
            self.phase, self.phase_started = phase, time.perf_counter()
        body = json.dumps({"phase": phase, "done": done, "total": total})
        self._submit(self.redis.set(progress_key(self.job_id), body, ex=self.ttl_s))

    def finish_phase(self) -> None:
        if self.phase is None:
            return
        field = f"{self.kind}:{self.phase}"
        self._submit(
            self.redis.hincrbyfloat(STATS_KEY, f"phase_sum:{field}", time.perf_counter() - self.phase_started)
        )
        self._submit(self.redis.hincrby(STATS_KEY, f"phase_count:{field}", 1))
        self.phase = None

    def _submit(self, coroutine: Any) -> None:
        asyncio.run_coroutine_threadsafe(coroutine, self.loop)


def _operate(
    engine: Engine, kind: JobKind, body: dict[str, Any], progress: ProgressFn, cancelled: CancelledFn
) -> BaseModel:
    if kind == "infer":
        return engine.infer(InferRequest.model_validate(body), progress, cancelled)
    if kind == "next-action":
        return engine.next_action(NextActionRequest.model_validate(body), progress, cancelled)
    return engine.check(CheckRequest.model_validate(body))


def _outcome(
    engine: Engine, kind: JobKind, body: dict[str, Any], progress: ProgressFn, cancelled: CancelledFn
) -> dict[str, Any]:
    """A finished job's outcome; input errors are outcomes too (the client's: 422), not crashes."""
    try:
        result = _operate(engine, kind, body, progress, cancelled)
    except PrecondError as exc:
        error = {"type": exc.kind, "message": exc.message, "field": exc.field}
        return {"status": "failed", "error": error, "sandbox_limit": isinstance(exc, ResourceLimit)}
    return {"status": "succeeded", "result": result.model_dump(mode="json")}


async def run_operation(ctx: dict[str, Any], kind: JobKind, body: dict[str, Any]) -> dict[str, Any]:
    """arq entry point. On cancellation (abort, timeout, shutdown) the engine is told and awaited to stop."""
    settings: Settings = ctx["settings"]
    redis: Redis[bytes] = ctx["redis"]
    job_id: str = ctx["job_id"]
    loop = asyncio.get_running_loop()
    reporter = ProgressReporter(redis, job_id, kind, loop, settings.result_ttl_s)
    stop = threading.Event()
    future = loop.run_in_executor(None, _outcome, ctx["engine"], kind, body, reporter, stop.is_set)
    try:
        outcome = await asyncio.shield(future)
    except asyncio.CancelledError:
        stop.set()
        await asyncio.wait([future])
        raise
    finally:
        reporter.finish_phase()
    sandbox_limit = outcome.pop("sandbox_limit", False)
    # Bookkeeping only: arq stores the outcome itself right after this returns. A Redis blip here must not
    # turn a finished job into a failed one (arq would record the ConnectionError as the job's result).
    with contextlib.suppress(RedisError, OSError):
        if outcome["status"] == "succeeded":
            await ResultCache(redis, settings.cache_ttl_s).put(job_id, outcome["result"])
        if sandbox_limit:
            await redis.hincrby(STATS_KEY, "sandbox_failures", 1)
        await redis.hincrby(STATS_KEY, f"jobs:{kind}:{outcome['status']}", 1)
    return dict(outcome)
