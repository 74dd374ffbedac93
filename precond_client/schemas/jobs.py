"""Jobs and errors: a job's kind, state, progress and status; the error body every failure has."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from precond_client.schemas.check import Blocked
from precond_client.schemas.common import StrictBody

JobKind = Literal["infer", "next-action", "check", "validate", "reinfer", "train-policy"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class ErrorInfo(StrictBody):
    type: str
    message: str
    field: str | None = None
    blocked: list[Blocked] | None = Field(
        default=None, description="`blocks_demonstration`: every demonstrated call the new rules would refuse (the "
        "rule and where), so that a reviewer sees which demonstrations it blocks. The ways out: `force: true` "
        "(they become the rule's known exceptions), a `reject` edit of the rule (or the set stored without it), "
        "or the demonstrations left out.")


class ErrorResponse(StrictBody):
    error: ErrorInfo
    request_id: str


class JobProgress(StrictBody):
    phase: str = "queued"
    done: int = 0
    total: int = 0


class JobStatus(StrictBody):
    id: str
    kind: JobKind
    status: JobState
    progress: JobProgress = Field(default_factory=JobProgress)
    result: dict[str, Any] | None = None
    error: ErrorInfo | None = None
    wait_max_s: float | None = Field(
        default=None,
        description="In a POST's 202 only: the longest the server waits for a job before answering 202 "
        "(`PRECOND_WAIT_MAX_S`); a `?wait=` above it was cut to it. The job runs on: poll `Location`.",
    )
