"""Liveness, readiness and metrics, in the shapes orchestrators and Prometheus expect."""

from __future__ import annotations

import contextlib
import logging

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from redis.exceptions import RedisError

from precond.gateway.auth import refuse
from precond.gateway.deps import Services, ServicesDep
from precond.gateway.errors import ServiceError
from precond.jobs.queue.heartbeats import Heartbeat, live_workers
from precond.jobs.queue.keys import QUEUES
from precond.jobs.records import read_stats


async def _open_rate(request: Request) -> None:
    """The open routes' rate per source address (in this process: they must answer without Redis)."""
    services: Services = request.app.state.services
    source = request.client.host if request.client is not None else "-"
    refuse(services, "-", services.open_rate.take(source))


router = APIRouter(tags=["health"], dependencies=[Depends(_open_rate)])
HEALTH_PEEK_S = 0.5
log = logging.getLogger("precond.gateway")


@router.get("/health")
async def health(services: ServicesDep) -> dict[str, str]:
    """The process answers (whatever Redis does: that is /ready). It also says, when the workers' heartbeats
    can be read at once, whether any of them runs untrusted code without the kernel policy (read at most once
    a second: precond/gateway/worker_view.py), as a code: which workers, only in the logs."""
    return {"status": "ok", "sandbox": await services.workers.sandbox(HEALTH_PEEK_S)}


NOT_READY = {
    "no_worker": "no worker is live",
    "sandbox_unavailable": "no worker can confine untrusted code",
    "model_not_loaded": "no worker has its model loaded yet",
    "model_load_failed": "no worker could load its model",
}
"""The reasons /ready gives anybody: stable codes an orchestrator or a script can match. What lies behind them (a
worker's exception, paths, memory limits, CPU features) is for the operator: the logs, or /ready with an
operator's key (`precond keys create --operator`)."""


def _not_ready(workers: list[Heartbeat]) -> tuple[str, str] | None:
    """The reason code and the operator's details, or None when a live worker can take every kind of job."""
    if not workers:
        return "no_worker", "no worker heartbeat in Redis"
    usable = [w for w in workers if w.sandbox != "unavailable"]
    if not usable:
        return "sandbox_unavailable", f"{len(workers)} live: {workers[0].sandbox_error or 'unknown'}"
    if not any(w.model_loaded for w in usable):
        failed = [w.model_error for w in usable if w.model_error]
        if failed:  # a refused load says why (a memory limit, a missing file)
            return "model_load_failed", f"{len(workers)} live: {failed[0]}"
        return "model_not_loaded", f"{len(workers)} live, loading"
    return None


def _reads_details(services: Services, request: Request) -> bool:
    """An open gateway (no keys file: loopback only, one user) or an operator's key sees the details; a tenant's
    key, a bad key or none sees the code only (a failed key is counted like any failed authentication)."""
    if services.keys is None:
        return True
    scheme, _, key = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not key:
        return False
    try:
        return services.keys.record(key.strip()).operator
    except ServiceError:
        return False


@router.get("/ready")
async def ready(services: ServicesDep, request: Request) -> dict[str, object]:
    """Ready when Redis answers and a live worker can confine untrusted code and has its model loaded. Anybody
    learns ready or not and a reason code; the reason's details go to the log, and to an operator's key."""
    await services.redis.ping()
    workers = await live_workers(services.redis)
    reason = _not_ready(workers)
    if reason is not None:
        code, details = reason
        _READINESS.log(f"not ready ({code}): {details}")
        message = f"not ready: {NOT_READY[code]}"
        if _reads_details(services, request):
            message += f" ({details})"
        raise ServiceError(503, message, code, headers={"Retry-After": "5"})
    _READINESS.log("ready")
    usable = [w for w in workers if w.sandbox != "unavailable"]
    return {"status": "ready", "workers": len(workers), "model_loaded": sum(w.model_loaded for w in usable),
            "sandbox_unconfined": sum(w.sandbox == "unconfined" for w in usable)}


class _LoggedReadiness:
    """This process's last logged readiness: logged when it changes, so a probe every few seconds does not flood
    the log."""

    def __init__(self) -> None:
        self.last = ""

    def log(self, state: str) -> None:
        if state != self.last:
            self.last = state
            log.warning("readiness: %s", state)


_READINESS = _LoggedReadiness()


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
