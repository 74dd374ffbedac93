"""What `/health` says of the workers' sandboxes, read from their heartbeats at most once a second.

Reading the heartbeats scans the queue Redis's keys, several round trips on a busy keyspace. A liveness probe
polled every few milliseconds (or flooded by one caller) must not turn each poll into that scan: the first
poll after the view has aged starts one read, concurrent polls share it, and the rest answer from memory.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Final

from redis.asyncio import Redis
from redis.exceptions import RedisError

from precond.jobs.queue.heartbeats import live_workers

UNKNOWN: Final = "unknown"
UNCONFINED: Final = "unconfined"
log = logging.getLogger("precond.gateway")


class WorkerView:
    def __init__(self, redis: Redis[bytes], max_age_s: float = 1.0) -> None:
        self._redis, self._max_age_s = redis, max_age_s
        self._value, self._at = UNKNOWN, float("-inf")
        self._reading: asyncio.Task[None] | None = None

    async def sandbox(self, wait_s: float) -> str:
        """"confined", "unconfined" or "unknown" (no heartbeat read within `wait_s`): a code anybody may read;
        which workers run unconfined goes to the log."""
        if time.monotonic() - self._at < self._max_age_s:
            return self._value
        if self._reading is None or self._reading.done():
            self._reading = asyncio.create_task(self._read())
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._reading), wait_s)
        return self._value if time.monotonic() - self._at < self._max_age_s else UNKNOWN

    async def _read(self) -> None:
        try:
            workers = await live_workers(self._redis)
        except (RedisError, OSError, TimeoutError):
            self._value = UNKNOWN
        else:
            unconfined = [w.id for w in workers if w.sandbox == "unconfined"]
            if unconfined and self._value != UNCONFINED:
                log.error("UNCONFINED on %s (SANDBOX_ALLOW_UNCONFINED: development only)", ", ".join(unconfined))
            self._value = UNCONFINED if unconfined else "confined"
        self._at = time.monotonic()

    def close(self) -> None:
        if self._reading is not None:
            self._reading.cancel()
