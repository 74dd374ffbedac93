"""Job-completion notices: waiting requests wake when their job's end is stored, not on a timer.

Each gateway process subscribes to a channel of its own (`jobs.queue.notices.notice_channel`), and every request
that waits on a job names that channel among the job's waiters when it submits the job (precond/gateway/queue.py). The
worker's script that stores the job's end publishes on those channels only, with the end as stored (its
result and progress, when small), so the one process that waits wakes and answers without reading it back.
Notices are an optimisation, never the only way: a waiter whose notice carries no end re-reads the job's
state, re-reads it once a second anyway (a lost notice, or a job arq fails without running it, costs at most
a second), and polls at `wait_poll_s` while the subscription is down (Redis restarting).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field

from redis.asyncio import ConnectionPool, Redis
from redis.exceptions import RedisError

from precond.jobs.queue.notices import notice_channel, read_notice

log = logging.getLogger("precond.gateway")

RECONNECT_S = 1.0
"""Pause between attempts to (re)subscribe while Redis is unreachable."""


@dataclass(eq=False)  # a watch is itself, not its contents: kept in sets
class Watch:
    """One request's watch on a job: set when a notice comes; `end` is the (progress, arq result) it carried."""

    event: asyncio.Event = field(default_factory=asyncio.Event)
    end: tuple[bytes, bytes] | None = None


class Completions:
    def __init__(self, dsn: str) -> None:
        # Its own connection: a subscribed connection can do nothing else, and reads here block for long.
        self._redis: Redis[bytes] = Redis(
            connection_pool=ConnectionPool.from_url(dsn, socket_connect_timeout=2, health_check_interval=30)
        )
        self.channel = notice_channel(uuid.uuid4().hex)
        """Where this process hears of the ends of the jobs its requests wait on (a job names it as a waiter)."""
        self._watches: dict[str, set[Watch]] = {}
        self._task: asyncio.Task[None] | None = None
        self.subscribed = False

    def start(self) -> None:
        self._task = asyncio.create_task(self._listen())

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self._redis.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    @contextlib.contextmanager
    def watch(self, job_id: str) -> Iterator[Watch]:
        """A watch set whenever `job_id`'s end is announced while the block runs. Enter before the job is
        submitted (or its state read)."""
        watch = Watch()
        self._watches.setdefault(job_id, set()).add(watch)
        try:
            yield watch
        finally:
            watches = self._watches.get(job_id, set())
            watches.discard(watch)
            if not watches:
                self._watches.pop(job_id, None)

    def _wake(self, message: bytes) -> None:
        job_id, progress, result = read_notice(message)
        for watch in self._watches.get(job_id, ()):
            if progress is not None and result is not None:
                watch.end = (progress, result)
            watch.event.set()

    async def _listen(self) -> None:
        while True:
            pubsub = self._redis.pubsub()
            try:
                await pubsub.subscribe(self.channel)
                self.subscribed = True
                while True:
                    message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=1.0)
                    if message is not None and message["type"] == "message":
                        self._wake(message["data"])
            except (RedisError, OSError) as exc:
                if self.subscribed:
                    log.warning("job-completion subscription lost (%s); polling until it is back", exc)
            finally:
                self.subscribed = False
                with contextlib.suppress(RedisError, OSError):
                    await pubsub.aclose()  # type: ignore[attr-defined]
            # Everyone waiting may have missed a message while the subscription was down.
            for watches in self._watches.values():
                for watch in watches:
                    watch.event.set()
            await asyncio.sleep(RECONNECT_S)
