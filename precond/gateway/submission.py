"""How a request becomes a job, one way for every route: its id, the result cache, the static screen, the
tenant's job cap, the queue and the wait. The operations, a precondition set's check against its
demonstrations and a re-inference all come through `submit_job`, so they count the same metrics and refuse
with the same answers."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

from precond.gateway.auth import refusal_error
from precond.gateway.caller import Caller
from precond.gateway.deps import Services
from precond.gateway.errors import ServiceError
from precond.jobs.queue import keys
from precond.jobs.queue.kinds import tenant_private
from precond.jobs.queue.steps import QueueFull, TenantFull
from precond_client.schemas import JobKind, JobProgress, JobStatus

Screen = Callable[[], Awaitable[None]]
"""A check of the request that raises `ServiceError` (422) before anything is queued: run only when the job
must run, since a cached result passed it already."""


def job_keys(services: Services, caller: Caller, kind: JobKind, payload: dict[str, Any],
             model: str | None) -> tuple[keys.JobId, str]:
    """The request's job, and where its result is cached: under the job id, each tenant's own, unless the
    operator lets tenants share results (`PRECOND_SHARE_CACHE`) and the kind's result is not the tenant's alone."""
    job = keys.JobId(kind, caller.tag, keys.job_id(kind, payload, model, services.secret, caller.tag))
    shared = services.settings.share_cache and not tenant_private(kind, payload)
    return job, keys.cache_id(kind, payload, model, services.secret) if shared else job.value


async def cached_status(services: Services, kind: JobKind, job_id: str, cache_key: str) -> JobStatus | None:
    """The job's state when its result is cached (`succeeded`, counted as a cache hit), else None (not counted:
    the caller counts the miss once it goes on to submit)."""
    cached = await services.cache.get(cache_key)
    if cached is None:
        return None
    services.metrics.cache.labels(kind, "hit").inc()
    done = JobProgress(phase="done", done=1, total=1)
    return JobStatus.model_construct(id=job_id, kind=kind, status="succeeded", progress=done, result=cached)


async def submit_job(
    services: Services,
    caller: Caller,
    kind: JobKind,
    payload: dict[str, Any],
    model: str | None,
    wait_s: float | None,
    screen: Screen | None = None,
) -> JobStatus:
    """The job's state after waiting up to `wait_s` (capped by `PRECOND_WAIT_MAX_S`; None: the cap):
    `succeeded` with its result at once when the result is cached."""
    settings = services.settings
    job, cache_key = job_keys(services, caller, kind, payload, model)
    cached = await cached_status(services, kind, job.value, cache_key)
    if cached is not None:  # only a request that passed the screen and ran has a cached result
        return cached
    services.metrics.cache.labels(kind, "miss").inc()
    if screen is not None:
        await screen()
    timeout = settings.wait_max_s if wait_s is None else min(wait_s, settings.wait_max_s)
    try:
        status = await services.queue.submit(job, payload, cache_key, timeout, settings.wait_poll_s)
    except TenantFull as full:
        refusal = services.quotas.jobs_refusal(caller, full.count, settings.retry_after_s)
        raise refusal_error(services, caller.tag, refusal) from None
    except QueueFull as full:
        services.metrics.rejections.labels(caller.tag, "queue").inc()
        raise ServiceError(
            429, f"queue limit: queue {full} is full", "queue_full",
            headers={"Retry-After": str(settings.retry_after_s)},
        ) from None
    if status is None:
        raise ServiceError(503, "the job vanished from the queue backend", headers={"Retry-After": "1"})
    return status
