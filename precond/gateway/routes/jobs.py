"""Polling and cancelling jobs that outlived their request's wait bound."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from precond.gateway.auth import RATE_LIMITED, CurrentCaller
from precond.gateway.caller import Caller
from precond.gateway.deps import ServicesDep
from precond.gateway.errors import ServiceError
from precond.jobs.queue.keys import JobId
from precond_client.schemas import ErrorResponse, JobStatus

router = APIRouter(prefix="/jobs", tags=["jobs"])
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "Missing, unknown, revoked or expired API key."},
    404: {"model": ErrorResponse, "description": "No such job of yours (another tenant's job is not found either), "
          "or its result expired."},
    429: RATE_LIMITED,
}


@router.get("/{job_id}", response_model=JobStatus, responses=NOT_FOUND)
async def get_job(job_id: str, services: ServicesDep, caller: CurrentCaller) -> JobStatus:
    status = await services.queue.status(_own(job_id, caller))
    if status is None:
        raise ServiceError(404, f"no job {job_id}")
    return status


@router.delete("/{job_id}", response_model=JobStatus, responses=NOT_FOUND)
async def cancel_job(job_id: str, services: ServicesDep, caller: CurrentCaller) -> JobStatus:
    """Cancel a queued or running job; a finished job is returned unchanged."""
    status = await services.queue.cancel(_own(job_id, caller), confirm_s=min(2.0, services.settings.wait_max_s))
    if status is None:
        raise ServiceError(404, f"no job {job_id}")
    return status


def _own(job_id: str, caller: Caller) -> JobId:
    """The caller's job `job_id` names; another tenant's job answers exactly as a job that does not exist."""
    job = JobId.read(job_id)
    if job is None or job.tenant != caller.tag:
        raise ServiceError(404, f"no job {job_id}")
    return job
