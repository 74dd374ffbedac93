"""Job-completion notifications: waiting requests wake when their job's result is stored, not on a timer.

Workers publish on `precond:done:<job id>` right after arq records a result (`worker.runner._announce`). Each
gateway process holds one pattern subscription for all of them and wakes the requests waiting on that id.
Notifications are an optimisation, never the source of truth: a waiter re-reads the job's state from Redis
after every wake-up, polls at `wait_poll_s` while the subscription is down (Redis restarting), and once a
second even while it is up, so a lost message (or a job arq fails without running it) costs at most a second.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterator

from redis.asyncio import ConnectionPool, Redis
from redis.exceptions import RedisError

from jobs.keys import DONE_PREFIX

log = logging.getLogger("precond.gateway")

RECONNECT_S = 1.0
"""Pause between attempts to (re)subscribe while Redis is unreachable."""


class Completions:
    def __init__(self, dsn: str) -> None:
        # Its own connection: a subscribed connection can do nothing else, and reads here block for long.
        self._redis: Redis[bytes] = Redis(
            connection_pool=ConnectionPool.from_url(dsn, socket_connect_timeout=2, health_check_interval=30)
        )
        self._waiters: dict[str, set[asyncio.Event]] = {}
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
    def watch(self, job_id: str) -> Iterator[asyncio.Event]:
        """An event set whenever `job_id` is announced while the block runs. Enter before reading the state."""
        event = asyncio.Event()
        self._waiters.setdefault(job_id, set()).add(event)
        try:
            yield event
        finally:
            waiters = self._waiters.get(job_id, set())
            waiters.discard(event)
            if not waiters:
                self._waiters.pop(job_id, None)

    def _wake(self, channel: bytes) -> None:
        job_id = channel.decode(errors="replace").removeprefix(DONE_PREFIX)
        for event in self._waiters.get(job_id, ()):
            event.set()

    async def _listen(self) -> None:
        while True:
            pubsub = self._redis.pubsub()
            try:
                await pubsub.psubscribe(f"{DONE_PREFIX}*")
                self.subscribed = True
                while True:
                    message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=1.0)
                    if message is not None and message["type"] == "pmessage":
                        self._wake(message["channel"])
            except (RedisError, OSError) as exc:
                if self.subscribed:
                    log.warning("job-completion subscription lost (%s); polling until it is back", exc)
            finally:
                self.subscribed = False
                with contextlib.suppress(RedisError, OSError):
                    await pubsub.aclose()  # type: ignore[attr-defined]
            # Everyone waiting may have missed a message while the subscription was down.
            for waiters in self._waiters.values():
                for event in waiters:
                    event.set()
            await asyncio.sleep(RECONNECT_S)
