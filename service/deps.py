"""What a request handler needs from the app, built once in the lifespan and handed out by dependency."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from arq.connections import ArqRedis
from fastapi import Depends, Request

from jobs.cache import ResultCache
from service.api_keys import KeyStore
from service.offload import CheckPool
from service.prometheus import Metrics
from service.queue import JobQueue
from service.quotas import Quotas, SourceBuckets
from service.set_store import SetStore
from service.settings import GatewaySettings
from service.worker_view import WorkerView


@dataclass(frozen=True)
class Services:
    settings: GatewaySettings
    redis: ArqRedis
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


async def _services(request: Request) -> Services:
    """Async on purpose: FastAPI runs a plain `def` dependency in its thread pool, a round trip per request."""
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(_services)]
