"""The gateway: FastAPI app that validates, caches, queues and waits; it never runs the engine itself.

It must stay free of torch (the test suite checks sys.modules), so it can start in milliseconds, scale apart
from the workers, and run on machines without the model.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from arq.connections import ArqRedis
from fastapi import FastAPI
from redis.asyncio import ConnectionPool

from jobs.cache import ResultCache
from jobs.settings import GatewaySettings, get_gateway_settings
from service import errors
from service.completions import Completions
from service.deps import Services
from service.metrics import Metrics
from service.middleware import BodyLimit, RequestContext
from service.queue import JobQueue
from service.routes import health, operations
from service.routes import jobs as job_routes

DESCRIPTION = """Infer verified action preconditions from demonstrations with a code model, pick next actions
that satisfy them, and check proposed actions against them ("Code Models are Zero-shot Precondition
Reasoners"). POSTs wait up to `?wait=` seconds; a job not finished by then answers 202 with `Location:
/jobs/{id}`. Every error is `{"error": {"type", "message", "field"?}, "request_id"}`."""


def create_app(settings: GatewaySettings | None = None) -> FastAPI:
    settings = settings or get_gateway_settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # No connection is made here: the gateway starts (and answers 503) while Redis is down.
        dsn = settings.redis_dsn
        redis = ArqRedis(ConnectionPool.from_url(dsn, socket_connect_timeout=2, socket_timeout=10))
        cache = ResultCache(redis, settings.cache_ttl_s)
        completions = Completions(dsn)
        completions.start()
        queue = JobQueue(redis, cache, completions, settings.queue_max_jobs, settings.result_ttl_s)
        app.state.services = Services(settings, redis, cache, queue, metrics)
        yield
        await completions.close()
        await redis.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    app = FastAPI(
        title="Precondition reasoning service", version="0.1.0", description=DESCRIPTION, lifespan=lifespan
    )
    for router in (operations.router, job_routes.router, health.router):
        app.include_router(router)
    errors.install(app, settings.retry_after_s)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(RequestContext, metrics=metrics)
    return app
