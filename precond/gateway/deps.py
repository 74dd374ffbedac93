"""What a request handler needs from the app, built once in the lifespan and handed out by dependency."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from redis.asyncio import Redis

from precond.gateway.api_keys import KeyStore
from precond.gateway.fast_check import CheckMemo
from precond.gateway.offload import CheckPool
from precond.gateway.prometheus import Metrics
from precond.gateway.queue import JobQueue
from precond.gateway.quotas import Quotas, SourceBuckets
from precond.gateway.set_store import SetStore
from precond.gateway.settings import GatewaySettings
from precond.gateway.worker_view import WorkerView
from precond.jobs.cache import ResultCache


@dataclass(frozen=True)
class Services:
    settings: GatewaySettings
    redis: Redis[bytes]
    cache: ResultCache
    queue: JobQueue
    metrics: Metrics
    quotas: Quotas
    secret: bytes
    keys: KeyStore | None
    sets: SetStore
    checks: CheckPool
    open_rate: SourceBuckets
    workers: WorkerView
    check_memo: CheckMemo


async def _services(request: Request) -> Services:
    """Async on purpose: FastAPI runs a plain `def` dependency in its thread pool, a round trip per request."""
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(_services)]
