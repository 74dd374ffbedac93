"""Typed errors of the client: one class per thing a caller does something different about.

Every error carries what the gateway said (`status`, `type`, `message`, `field`, `request_id`); the class
says what to do: fix the request (`InvalidInput`), the key (`Unauthorized`), wait (`RateLimited`,
`Unavailable`: the client already retried them), or look elsewhere (`NotFound`).
"""

from __future__ import annotations

from typing import Any


class PrecondError(Exception):
    """Base of every error the client raises (transport failures included, as `Unavailable`)."""

    def __init__(
        self,
        message: str,
        *,
        status: int | None = None,
        type: str | None = None,
        field: str | None = None,
        request_id: str | None = None,
        job_id: str | None = None,
    ) -> None:
        super().__init__(message if field is None else f"{message} (field {field})")
        self.message = message
        self.status = status
        self.type = type
        self.field = field
        self.request_id = request_id
        self.job_id = job_id


class InvalidInput(PrecondError):
    """The request cannot be used (HTTP 422, 413 or 400, or a job failing on its input): `field` names where
    (e.g. `demonstrations[2]`), `message` says what."""


class Unauthorized(PrecondError):
    """HTTP 401: the API key is missing, unknown, revoked or expired (`message` says which)."""


class NotFound(PrecondError):
    """HTTP 404: no such job of this tenant (another tenant's job reads the same), or its result expired."""


class Cancelled(PrecondError):
    """HTTP 409 / job status `cancelled`: the job was cancelled."""


class Conflict(PrecondError):
    """HTTP 409 with type `conflict`: the precondition set has a newer version than the one you edited or
    re-inferred from (`base_version`); read the latest and try again."""


class RateLimited(PrecondError):
    """HTTP 429 after the last retry: `limit` is the limit's type (`rate_limited`, `jobs_limited`,
    `queue_full`), `retry_after` the seconds the gateway asked to wait (None when it said nothing)."""

    def __init__(self, message: str, *, retry_after: float | None = None, **info: Any) -> None:
        super().__init__(message, **info)
        self.limit = self.type
        self.retry_after = retry_after


class Unavailable(PrecondError):
    """HTTP 503 after the last retry (Redis down or full, no model, a sandbox failure), or the service cannot
    be reached at all; `retry_after` as for `RateLimited`."""

    def __init__(self, message: str, *, retry_after: float | None = None, **info: Any) -> None:
        super().__init__(message, **info)
        self.retry_after = retry_after


class JobTimeout(PrecondError):
    """The job was not done within the client's `timeout`; it goes on (cancel it with `cancel(job_id)`)."""


ERROR_BY_STATUS: dict[int, type[PrecondError]] = {
    400: InvalidInput,
    401: Unauthorized,
    404: NotFound,
    409: Cancelled,
    413: InvalidInput,
    422: InvalidInput,
    429: RateLimited,
    503: Unavailable,
}

ERROR_BY_JOB_TYPE: dict[str, type[PrecondError]] = {
    "invalid_input": InvalidInput,
    "invalid_program": InvalidInput,
    "unknown_action": InvalidInput,
    "resource_limit": InvalidInput,
    "work_budget": InvalidInput,
    "model_unavailable": Unavailable,
    "sandbox_failure": Unavailable,
    "unavailable": Unavailable,
    "cancelled": Cancelled,
    "conflict": Conflict,
    "blocks_demonstration": InvalidInput,
    "sets_limited": InvalidInput,
}
"""A failed job's `error.type` (GET /jobs/{id}) → the class its POST would have raised."""
