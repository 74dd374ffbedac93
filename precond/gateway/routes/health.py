"""Liveness, readiness and metrics, in the shapes orchestrators and Prometheus expect."""

from __future__ import annotations

import contextlib

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from redis.exceptions import RedisError

from precond.gateway.auth import refuse
from precond.gateway.deps import Services, ServicesDep
from precond.gateway.errors import ServiceError
from precond.jobs.queue.heartbeats import live_workers
from precond.jobs.queue.keys import QUEUES
from precond.jobs.records import read_stats


async def _open_rate(request: Request) -> None:
    """The open routes' rate per source address (in this process: they must answer without Redis)."""
    services: Services = request.app.state.services
    source = request.client.host if request.client is not None else "-"
    refuse(services, "-", services.open_rate.take(source))


router = APIRouter(tags=["health"], dependencies=[Depends(_open_rate)])
HEALTH_PEEK_S = 0.5


@router.get("/health")
async def health(services: ServicesDep) -> dict[str, str]:
    """The process answers (whatever Redis does: that is /ready). It also says, when the workers' heartbeats
    can be read at once, whether any of them runs untrusted code without the kernel policy (read at most once
    a second: precond/gateway/worker_view.py)."""
    return {"status": "ok", "sandbox": await services.workers.sandbox(HEALTH_PEEK_S)}


@router.get("/ready")
async def ready(services: ServicesDep) -> dict[str, object]:
    """Ready when Redis answers and a live worker can confine untrusted code and has its model loaded."""
    await services.redis.ping()
    workers = await live_workers(services.redis)
    usable = [w for w in workers if w.sandbox != "unavailable"]
    if workers and not usable:
        reason = workers[0].sandbox_error or "unknown"
        raise ServiceError(
            503, f"no worker can confine untrusted code ({len(workers)} live): {reason}", headers={"Retry-After": "5"}
        )
    loaded = sum(w.model_loaded for w in usable)
    if not loaded:
        failed = [w.model_error for w in usable if w.model_error]
        why = f": {failed[0]}" if failed else ""  # a refused load says why (a memory limit, a missing file)
        raise ServiceError(
            503, f"no worker with a loaded model ({len(workers)} live){why}", headers={"Retry-After": "5"}
        )
    unconfined = sum(w.sandbox == "unconfined" for w in usable)
    return {"status": "ready", "workers": len(workers), "model_loaded": loaded, "sandbox_unconfined": unconfined}


@router.get("/metrics", include_in_schema=False)
async def metrics(services: ServicesDep) -> Response:
    # Gateway metrics stay useful while Redis is down; the cluster gauges then keep their last value.
    with contextlib.suppress(RedisError):
        await _read_cluster_metrics(services)
    return Response(generate_latest(services.metrics.registry), media_type=CONTENT_TYPE_LATEST)


async def _read_cluster_metrics(services: Services) -> None:
    metrics = services.metrics
    for queue in QUEUES:
        metrics.queue_depth.labels(queue).set(await services.queue.depth(queue))
    workers = await live_workers(services.redis)
    for loaded in (True, False):
        metrics.workers.labels(str(loaded).lower()).set(sum(w.model_loaded == loaded for w in workers))
    metrics.worker_stats.snapshot = await read_stats(services.redis)
