"""What a request handler needs from the app, built once in the lifespan and handed out by dependency."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from arq.connections import ArqRedis
from fastapi import Depends, Request

from jobs.cache import ResultCache
from jobs.settings import GatewaySettings
from service.auth import KeyStore
from service.metrics import Metrics
from service.queue import JobQueue
from service.quotas import Quotas
from service.sets import SetStore


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


def _services(request: Request) -> Services:
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(_services)]
