"""Errors that carry a user-facing meaning (type, field) from wherever they arise to the API's one error shape."""

from __future__ import annotations


class PrecondError(Exception):
    """An error the caller can act on; `kind` and `field` end up verbatim in the API's error body."""

    kind = "error"

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class InvalidInput(PrecondError):
    """The request is well-formed JSON but its content cannot be used (HTTP 422)."""

    kind = "invalid_input"


class InvalidProgram(InvalidInput):
    """A spec, demonstration or history does not parse or raises when run."""

    kind = "invalid_program"


class ResponseTooLarge(InvalidInput):
    """The answer would exceed the deployment's bound (`PRECOND_MAX_RESPONSE_BYTES`)."""

    kind = "response_too_large"


class BlocksDemonstration(InvalidInput):
    """A rule would have refused a demonstrated call (an edit, or a required rule under new demonstrations)."""

    kind = "blocks_demonstration"


class SetsLimited(InvalidInput):
    """A precondition set at one of its bounds (`PRECOND_MAX_SET_VERSIONS`, `PRECOND_MAX_SET_BYTES`)."""

    kind = "sets_limited"


class Conflict(PrecondError):
    """The precondition set got a new version since the one this job started from (HTTP 409)."""

    kind = "conflict"


class NotFound(PrecondError):
    """What the job names is not (or no longer) the tenant's: a trained policy deleted after it was named
    (HTTP 404, as the gateway answers for one that never existed)."""

    kind = "not_found"


class UnknownAction(InvalidInput):
    kind = "unknown_action"


class ResourceLimit(PrecondError):
    """Untrusted code hit a sandbox limit (time, memory, output...)."""

    kind = "resource_limit"


class ModelUnavailable(PrecondError):
    kind = "model_unavailable"


class SandboxFailure(PrecondError):
    """The sandbox itself failed (its process ended without an answer, or untrusted code cannot be confined
    here): the service's problem, not the request's (HTTP 503), and never kept as the request's result."""

    kind = "sandbox_failure"


class Cancelled(PrecondError):
    """The client cancelled the job; raised between phases and between decode steps."""

    kind = "cancelled"
