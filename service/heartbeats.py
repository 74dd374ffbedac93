"""Worker heartbeats: each worker process rewrites its own expiring key; readiness and metrics read them.

Expiring keys rather than a registry that workers join and leave: a SIGKILLed worker cannot say goodbye, and
its key simply lapses after three missed beats.
"""

from __future__ import annotations

from pydantic import BaseModel
from redis.asyncio import Redis

from service.keys import WORKERS_PATTERN, worker_key


class Heartbeat(BaseModel):
    id: str
    host: str
    pid: int
    queues: list[str]
    model_loaded: bool
    model_error: str | None = None
    jobs_started: int = 0
    jobs_complete: int = 0


async def beat(redis: Redis[bytes], heartbeat: Heartbeat, ttl_s: float) -> None:
    await redis.set(worker_key(heartbeat.id), heartbeat.model_dump_json(), px=int(ttl_s * 1000))


async def live_workers(redis: Redis[bytes]) -> list[Heartbeat]:
    keys = [key async for key in redis.scan_iter(match=WORKERS_PATTERN, count=100)]
    raws = await redis.mget(keys) if keys else []
    return [Heartbeat.model_validate_json(raw) for raw in raws if raw is not None]
