"""What the sync and async clients share: endpoints, request bodies, answers → results or typed errors, and
the retry schedule. No I/O here, so both clients behave the same by construction."""

from __future__ import annotations

import json
import random
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import httpx
from pydantic import BaseModel, ValidationError

from precond_client.errors import (
    ERROR_BY_JOB_TYPE,
    ERROR_BY_STATUS,
    Cancelled,
    Conflict,
    InvalidInput,
    PrecondError,
    RateLimited,
    Unavailable,
)
from precond_client.schemas import (
    ADAPTER_REFERENCE,
    SET_REFERENCE,
    CheckRequest,
    CheckResponse,
    ErrorInfo,
    HistoryEvent,
    InferOptions,
    InferRequest,
    InferResponse,
    JobKind,
    JobProgress,
    JobStatus,
    NextActionOptions,
    NextActionRequest,
    NextActionResponse,
    PreconditionSet,
    PreconditionSetEdit,
    PreconditionSetReinfer,
    RuleEdit,
    ToolCall,
)
from precond_client.schemas.training import PolicyAdapter

Progress = Callable[[JobStatus], object]
"""Called with the job's status (its `progress`: phase, done, total) on the 202 and on every poll."""

RETRY_STATUSES = frozenset({429, 503})
SET_REFERENCE_RE = re.compile(SET_REFERENCE)
POLICY_REFERENCE_RE = re.compile(ADAPTER_REFERENCE)
Req = TypeVar("Req", bound=BaseModel)


@dataclass(frozen=True)
class Operation:
    kind: JobKind
    path: str
    request: type[BaseModel]
    response: type[BaseModel]


OPERATIONS: dict[type[BaseModel], Operation] = {
    InferRequest: Operation("infer", "/infer-preconditions", InferRequest, InferResponse),
    NextActionRequest: Operation("next-action", "/next-action", NextActionRequest, NextActionResponse),
    CheckRequest: Operation("check", "/check-actions", CheckRequest, CheckResponse),
}
RESPONSES: dict[JobKind, type[BaseModel]] = {op.kind: op.response for op in OPERATIONS.values()}
RESPONSES["reinfer"] = PreconditionSet
RESPONSES["train-policy"] = PolicyAdapter


@dataclass(frozen=True)
class Retry:
    """Bounded retries with exponential backoff and jitter; a `Retry-After` is a floor, never shortened.

    Retried: 429 (a limit), 503 (unavailable) and transport errors (connection refused or reset, timeouts).
    Safe for every call: identical POSTs share one job (its id is a hash of the request), GET and DELETE of a
    job are idempotent."""

    attempts: int = 5
    """Tries in all (1: never retry)."""
    base_s: float = 0.5
    max_s: float = 30.0
    jitter: float = 0.25
    """Each delay is stretched by a random factor in [1, 1 + jitter], so clients refused together spread out."""

    def delay(self, attempt: int, retry_after: float | None) -> float:
        """Seconds before try `attempt + 1` (attempt counts from 0)."""
        backoff = min(self.max_s, self.base_s * 2**attempt)
        floor = max(backoff, retry_after or 0.0)
        return float(floor * (1 + random.uniform(0, self.jitter)))


RetryHook = Callable[[PrecondError, float], object]
"""Called before each retry with the error that caused it and the seconds the client will sleep."""


def headers(api_key: str | None) -> dict[str, str]:
    base = {"User-Agent": "precond-client/0.1", "Accept": "application/json"}
    return base if api_key is None else {**base, "Authorization": f"Bearer {api_key}"}


def operation(request: BaseModel | Mapping[str, Any], expected: type[Req]) -> tuple[Req, Operation]:
    """The request as its model (a mapping is validated here: a bad field is `InvalidInput` before sending)."""
    return validated(request, expected), OPERATIONS[expected]


def validated(request: BaseModel | Mapping[str, Any], expected: type[Req]) -> Req:
    """A request model as is, or a mapping validated into one (a bad field: `InvalidInput`, nothing sent)."""
    if isinstance(request, BaseModel):
        if not isinstance(request, expected):
            raise TypeError(f"expected {expected.__name__}, got {type(request).__name__}")
        body = request
    else:
        try:
            body = expected.model_validate(dict(request))
        except ValidationError as exc:
            first = exc.errors()[0]
            field = ".".join(str(p) for p in first["loc"]) or "body"
            raise InvalidInput(first["msg"], type="invalid_input", field=field) from None
    return body


def set_path(reference: str, suffix: str = "") -> str:
    """`/precondition-sets/{reference}{suffix}`, the reference checked so it can never leave that path."""
    if not SET_REFERENCE_RE.match(reference):
        raise InvalidInput(f"not a precondition set reference: {reference[:80]!r} (expected ps_<24 hex>[@n])",
                           type="invalid_input", field="precondition_set")
    return f"/precondition-sets/{reference}{suffix}"


def policy_path(reference: str, suffix: str = "") -> str:
    """`/policies/{reference}{suffix}`, the reference checked so it can never leave that path."""
    if not POLICY_REFERENCE_RE.match(reference):
        raise InvalidInput(f"not a trained policy reference: {reference[:80]!r} (expected ad_<24 hex>[@n])",
                           type="invalid_input", field="adapter")
    return f"/policies/{reference}{suffix}"


def set_body(model: BaseModel) -> dict[str, Any]:
    """A set request's JSON: only the fields given, so the server's defaults stay the server's."""
    body: dict[str, Any] = model.model_dump(mode="json", exclude_unset=True)
    return body


def retry_after(response: httpx.Response) -> float | None:
    value = response.headers.get("Retry-After")
    try:
        return None if value is None else max(0.0, float(value))
    except ValueError:
        return None  # an HTTP date: the backoff alone decides


def error_from_response(response: httpx.Response) -> PrecondError:
    info: dict[str, Any] = {}
    request_id = response.headers.get("X-Request-Id")
    try:
        body = response.json()
        if isinstance(body, dict) and isinstance(body.get("error"), dict):
            info = body["error"]
            request_id = body.get("request_id") or request_id
    except (json.JSONDecodeError, UnicodeDecodeError):
        pass
    message = str(info.get("message") or response.text[:500] or response.reason_phrase)
    cls = ERROR_BY_STATUS.get(response.status_code, PrecondError)
    if response.status_code == 409 and info.get("type") == "conflict":
        cls = Conflict
    common: dict[str, Any] = {
        "status": response.status_code,
        "type": info.get("type"),
        "field": info.get("field"),
        "request_id": request_id,
        "job_id": response.headers.get("X-Job-Id"),
    }
    if cls in (RateLimited, Unavailable):
        return cls(message, retry_after=retry_after(response), **common)
    return cls(message, **common)


def transport_error(exc: httpx.TransportError, url: str) -> Unavailable:
    return Unavailable(f"cannot reach {url}: {type(exc).__name__}: {exc}", type="transport")


def job_error(status: JobStatus) -> PrecondError:
    """The error a failed or cancelled job reports on `GET /jobs/{id}`."""
    if status.status == "cancelled":
        return Cancelled(f"job {status.id} was cancelled", type="cancelled", job_id=status.id, status=409)
    info = status.error or ErrorInfo(type="internal", message="job failed")
    cls = ERROR_BY_JOB_TYPE.get(info.type, PrecondError)
    return cls(info.message, type=info.type, field=info.field, job_id=status.id)


def submitted(response: httpx.Response, kind: JobKind) -> JobStatus:
    """200 (done, or a cache hit) or 202 (queued or running) as the job's status; any other answer raises."""
    if response.status_code == 202:
        return JobStatus.model_validate(response.json())
    if response.status_code == 200:
        return JobStatus(
            id=response.headers.get("X-Job-Id", ""),
            kind=kind,
            status="succeeded",
            progress=JobProgress(phase="done", done=1, total=1),  # never `done 0 0`: it finished
            result=response.json(),
        )
    raise error_from_response(response)


def finished(status: JobStatus) -> bool:
    return status.status in ("succeeded", "failed", "cancelled")


def result(status: JobStatus, expected: type[Req]) -> Req:
    if status.status != "succeeded":
        raise job_error(status)
    return expected.model_validate(status.result or {})


@dataclass(frozen=True)
class Polling:
    """How `GET /jobs/{id}` is polled while a job runs: from `first_s`, growing by `factor`, up to `max_s`."""

    first_s: float = 0.1
    factor: float = 1.5
    max_s: float = 2.0

    def interval(self, polls: int) -> float:
        return float(min(self.max_s, self.first_s * self.factor**polls))


HistoryLike = str | Iterable[HistoryEvent | Mapping[str, Any]]
"""A history: a program (power users), events (`History`, `event(...)`s, or dicts of the same shape), or a
tool-calling agent's OpenAI chat messages (dicts with `role`; the service checks and renders them)."""


def history(value: HistoryLike) -> str | list[HistoryEvent] | list[dict[str, Any]]:
    if isinstance(value, str):
        return value
    items = list(value)
    if items and isinstance(items[0], Mapping) and "role" in items[0]:
        return [dict(item) for item in items if isinstance(item, Mapping)]
    return [item if isinstance(item, HistoryEvent) else validated(item, HistoryEvent) for item in items]


def edit_body(edits: Iterable[RuleEdit | Mapping[str, Any]], base_version: int | None, force: bool) -> dict[str, Any]:
    body = PreconditionSetEdit(edits=[validated(e, RuleEdit) for e in edits], base_version=base_version, force=force)
    return set_body(body)


def reinfer_body(demonstrations: Iterable[str], actions: Iterable[str] | None,
                 options: InferOptions | Mapping[str, Any] | None, base_version: int | None,
                 force: bool) -> dict[str, Any]:
    fields: dict[str, Any] = {"demonstrations": list(demonstrations), "base_version": base_version, "force": force}
    if actions is not None:
        fields["actions"] = list(actions)
    if options is not None:
        fields["options"] = validated(options, InferOptions)
    return set_body(validated(fields, PreconditionSetReinfer))


CallLike = str | ToolCall | Mapping[str, Any]
"""A proposed call: code (`system.REQUEST('city')`) or a tool call (`{"name", "arguments"}`)."""


def check_body(precondition_set: str, history_: HistoryLike, calls: Iterable[CallLike]) -> CheckRequest:
    return validated({"precondition_set": precondition_set, "history": history(history_), "calls": list(calls)},
                     CheckRequest)


def next_action_body(precondition_set: str, history_: HistoryLike, demonstrations: Iterable[str],
                     options: NextActionOptions | Mapping[str, Any] | None) -> NextActionRequest:
    fields: dict[str, Any] = {"precondition_set": precondition_set, "history": history(history_),
                              "demonstrations": list(demonstrations)}
    if options is not None:
        fields["options"] = validated(options, NextActionOptions)
    return validated(fields, NextActionRequest)
