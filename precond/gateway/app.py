"""The gateway: FastAPI app that validates, caches, queues and waits; it never runs the engine itself.

It must stay free of torch (the test suite checks sys.modules), so it can start in milliseconds, scale apart
from the workers, and run on machines without the model.
"""

from __future__ import annotations

import gc
import logging
import multiprocessing
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from redis.asyncio import ConnectionPool, Redis

from precond.gateway import errors
from precond.gateway.api_keys import KeyStore
from precond.gateway.completions import Completions
from precond.gateway.deps import Services
from precond.gateway.fast_check import CheckMemo
from precond.gateway.middleware import BlockedSources, BodyLimit, RequestContext
from precond.gateway.offload import CheckPool
from precond.gateway.prometheus import Metrics
from precond.gateway.queue import JobQueue
from precond.gateway.quotas import AuthLimit, Quotas, SourceBuckets
from precond.gateway.routes import health, operations, policies, sets, ui
from precond.gateway.routes import jobs as job_routes
from precond.gateway.set_store import SetStore
from precond.gateway.settings import GatewaySettings, get_gateway_settings
from precond.gateway.worker_view import WorkerView
from precond.jobs.cache import ResultCache
from precond.jobs.lifetime import die_with_parent
from precond.patches.redis_checkout import check_out_without_read
from precond.patches.redis_packing import pack_with_hiredis
from precond.patches.redis_sending import send_without_task

log = logging.getLogger("precond.gateway")
DESCRIPTION = """Infer verified action preconditions from demonstrations with a code model, pick next actions
that satisfy them, and check proposed actions against them ("Code Models are Zero-shot Precondition
Reasoners"). POSTs wait up to `?wait=` seconds; a job not finished by then answers 202 with `Location:
/jobs/{id}`. Every error is `{"error": {"type", "message", "field"?}, "request_id"}`."""


def create_app(settings: GatewaySettings | None = None) -> FastAPI:
    settings = settings or get_gateway_settings()
    metrics = Metrics()
    pack_with_hiredis()
    check_out_without_read()
    send_without_task()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Refuse to start without what keeps tenants apart (MissingSecret: job ids and cached results could not
        # be signed; a required keys file that is missing). No Redis connection is made here: the gateway
        # starts (and answers 503) while Redis is down.
        secret = settings.secret_bytes()
        keys = key_store(settings)
        spawner = multiprocessing.parent_process()
        if spawner is not None and spawner.pid is not None:  # one of uvicorn's `--workers`: it ends with
            die_with_parent(spawner.pid)  # uvicorn's supervisor, however that ends
        redis, cache_redis = _connections(settings)
        services, completions = _services(settings, metrics, redis, cache_redis, secret, keys)
        app.state.services = services
        # What start-up built lives as long as the process; a full collection walked all of it (tens of
        # thousands of objects, milliseconds on the event loop in some request's tail): frozen, it is not.
        gc.freeze()
        yield
        services.workers.close()
        services.checks.close()
        await completions.close()
        for connection in {id(redis): redis, id(cache_redis): cache_redis}.values():
            await connection.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose

    # The gateway's metrics are Prometheus' (`/metrics`); FastAPI's own OpenTelemetry, on by default, looked
    # up the global providers at every request (2% of a cache hit's CPU under cProfile) to find none configured.
    app = FastAPI(
        title="Precondition reasoning service", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
        telemetry={"tracing": False, "metrics": False, "logs": False},
    )
    for router in (operations.router, sets.router, policies.router, job_routes.router, health.router, ui.router):
        app.include_router(router)
    errors.install(app, settings.retry_after_s)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(BlockedSources)  # inside RequestContext: its refusals carry a request id and are counted
    app.add_middleware(RequestContext, metrics=metrics)
    return app


def _connections(settings: GatewaySettings) -> tuple[Redis[bytes], Redis[bytes]]:
    """The queue Redis, and the cache Redis (which may evict; the queue Redis never does): the same connection
    where they are one server. Nothing connects yet: the gateway starts (and answers 503) while Redis is down."""
    dsn = settings.redis_dsn
    redis: Redis[bytes] = Redis(
        connection_pool=ConnectionPool.from_url(dsn, socket_connect_timeout=2, socket_timeout=10))
    if settings.cache_redis_dsn == dsn:
        return redis, redis
    cache_redis: Redis[bytes] = Redis(connection_pool=ConnectionPool.from_url(
        settings.cache_redis_dsn, socket_connect_timeout=2, socket_timeout=10))
    return redis, cache_redis


def _services(settings: GatewaySettings, metrics: Metrics, redis: Redis[bytes], cache_redis: Redis[bytes],
              secret: bytes, keys: KeyStore | None) -> tuple[Services, Completions]:
    """What every route is served with, and the job-done notices' listener (started here, closed at shutdown)."""
    cache = ResultCache(cache_redis, settings.cache_ttl_s, secret, settings.recent_results_bytes)
    completions = Completions(settings.redis_dsn)
    completions.start()
    auth = AuthLimit(settings.auth_failures_per_s, settings.auth_failure_burst)
    quotas = Quotas(redis, settings.tenant_rate_per_s, settings.tenant_burst, settings.tenant_max_jobs, auth)
    queue = JobQueue(redis, cache, completions, settings.queue_max_jobs, settings.tenant_max_jobs,
                     settings.result_ttl_s)
    store = SetStore(redis, settings.max_sets_per_tenant, settings.max_set_versions, settings.max_set_bytes,
                     settings.max_set_bytes_per_tenant)
    pool = CheckPool(settings.check_processes, settings.tenant_check_processes)
    open_rate = SourceBuckets(settings.open_rate_per_s, settings.open_burst)
    services = Services(settings, redis, cache, queue, metrics, quotas, secret, keys, store, pool, open_rate,
                        WorkerView(redis), CheckMemo())
    return services, completions


def key_store(settings: GatewaySettings) -> KeyStore | None:
    if settings.api_keys_file is None:
        if settings.require_auth:
            raise SystemExit("PRECOND_REQUIRE_AUTH is set but PRECOND_API_KEYS_FILE is not: refusing to start open")
        log.warning("no API keys (PRECOND_API_KEYS_FILE unset): the API is open to anyone who can reach it")
        return None
    try:
        store = KeyStore(settings.api_keys_file)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"PRECOND_API_KEYS_FILE={settings.api_keys_file}: {exc}") from exc
    if settings.require_auth and not store.has_keys():
        raise SystemExit(f"PRECOND_REQUIRE_AUTH is set and {settings.api_keys_file} holds no key")
    return store
