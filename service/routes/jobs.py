"""Polling and cancelling jobs that outlived their request's wait bound."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from schemas.api import ErrorResponse, JobStatus
from service.deps import ServicesDep
from service.errors import ServiceError

router = APIRouter(prefix="/jobs", tags=["jobs"])
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "No such job (or its result expired)."}
}


@router.get("/{job_id}", response_model=JobStatus, responses=NOT_FOUND)
async def get_job(job_id: str, services: ServicesDep) -> JobStatus:
    status = await services.queue.status(job_id)
    if status is None:
        raise ServiceError(404, f"no job {job_id}")
    return status


@router.delete("/{job_id}", response_model=JobStatus, responses=NOT_FOUND)
async def cancel_job(job_id: str, services: ServicesDep) -> JobStatus:
    """Cancel a queued or running job; a finished job is returned unchanged."""
    status = await services.queue.cancel(job_id, confirm_s=min(2.0, services.settings.wait_max_s))
    if status is None:
        raise ServiceError(404, f"no job {job_id}")
    return status
