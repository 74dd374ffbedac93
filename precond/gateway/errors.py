"""Every failure leaves the gateway in one JSON shape, `ErrorResponse`, with the request id beside it.

Clients of a queueing service see errors from three places (validation here, Redis, the engine in a
worker); mapping them all in one module keeps the status codes consistent: bad input is always a 4xx.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import OutOfMemoryError  # type: ignore[attr-defined]  # types-redis predates it
from redis.exceptions import TimeoutError as RedisTimeoutError
from starlette.exceptions import HTTPException

from precond.gateway.offload import PoolBroken
from precond_client.schemas import Blocked, ErrorInfo, ErrorResponse
from precond_client.schemas import errors as engine_errors

log = logging.getLogger("precond.gateway")

_TYPE_BY_STATUS = {
    400: "bad_request",
    401: "unauthorized",
    404: "not_found",
    405: "method_not_allowed",
    413: "body_too_large",
    415: "unsupported_media_type",
    429: "queue_full",
    503: "unavailable",
}


class ServiceError(HTTPException):
    """An HTTPException with a machine-readable type; FastAPI re-raises these untouched from body parsing."""

    def __init__(
        self, status: int, message: str, type_: str | None = None, headers: dict[str, str] | None = None,
        field: str | None = None, blocked: list[Blocked] | None = None,
    ) -> None:
        super().__init__(status_code=status, detail=message, headers=headers)
        self.type = type_ or _TYPE_BY_STATUS.get(status, "error")
        self.field = field
        self.blocked = blocked


def request_id(request: Request) -> str:
    return str(getattr(request.state, "request_id", ""))


MAX_MESSAGE_CHARS = 1000
MAX_FIELD_CHARS = 200


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


MAX_BLOCKED = 64
"""Blocked calls an error lists (`blocks_demonstration`); its message counts them all."""


def bounded(info: ErrorInfo) -> ErrorInfo:
    """Messages and fields cut to a bounded size: they may quote the input (an unknown 1 MB action name)."""
    return ErrorInfo(
        type=_cut(info.type, MAX_FIELD_CHARS),
        message=_cut(info.message, MAX_MESSAGE_CHARS),
        field=None if info.field is None else _cut(info.field, MAX_FIELD_CHARS),
        blocked=None if info.blocked is None else [b.model_copy(update={
            "rule": _cut(b.rule, MAX_FIELD_CHARS), "call": None if b.call is None else _cut(b.call, MAX_FIELD_CHARS)})
            for b in info.blocked[:MAX_BLOCKED]],
    )


def error_response(
    request: Request, status: int, info: ErrorInfo, headers: dict[str, str] | None = None
) -> JSONResponse:
    body = ErrorResponse(error=bounded(info), request_id=request_id(request))
    return JSONResponse(body.model_dump(exclude_none=True), status_code=status, headers=headers)


def status_for(info: ErrorInfo) -> int:
    """HTTP status of a failed job: the engine's input errors are the client's (422), not ours (500)."""
    for cls in _subclasses(engine_errors.PrecondError):
        if cls.kind == info.type:
            if issubclass(cls, engine_errors.ModelUnavailable | engine_errors.SandboxFailure):
                return 503
            if issubclass(cls, engine_errors.Conflict):
                return 409
            if issubclass(cls, engine_errors.NotFound):
                return 404
            if issubclass(cls, engine_errors.InvalidInput | engine_errors.ResourceLimit):
                return 422
    return 500


def _subclasses(cls: type[engine_errors.PrecondError]) -> list[type[engine_errors.PrecondError]]:
    found = [cls]
    for sub in cls.__subclasses__():
        found += _subclasses(sub)
    return found


_PYDANTIC_PREFIX = re.compile(r"^(Value error|Assertion failed), ")
"""How pydantic introduces the message of a validator's ValueError: not the service's words."""

_UNION_TAGS = {"text", "events", "openai"}
"""pydantic's names for the forms of `history` (schemas.History): not part of the field's path."""


def _field(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc]
    parts = parts[1:] if parts[:1] in (["body"], ["query"], ["path"]) else parts
    if parts[:1] == ["history"] and parts[1:2] and parts[1] in _UNION_TAGS:
        del parts[1]
        if parts[1:2] and parts[1].isdigit():  # history[3].act, as the gateway's own event checks name it
            parts[:2] = [f"history[{parts[1]}]"]
    return ".".join(parts)


async def _json_error(request: Request, error: dict[str, Any]) -> ErrorInfo:
    """A body that is not JSON: the field is the body, the message says what and where (line, column)."""
    offset = error["loc"][1] if len(error["loc"]) > 1 and isinstance(error["loc"][1], int) else None
    reason = str((error.get("ctx") or {}).get("error", "invalid JSON"))
    where = ""
    if offset is not None:
        text = (await request.body()).decode("utf-8", errors="replace")[:offset]
        line = text.count("\n") + 1
        column = offset - (text.rfind("\n") + 1) + 1
        where = f" at line {line}, column {column} (character {offset})"
    return ErrorInfo(type="validation_error", message=f"body is not valid JSON: {reason}{where}", field="body")


async def _validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    first = exc.errors()[0]
    if first.get("type") == "json_invalid":
        return error_response(request, 422, await _json_error(request, first))
    field = _field(first["loc"]) or "body"  # the whole body: a form, a list, a bare string
    message = _PYDANTIC_PREFIX.sub("", str(first.get("msg", "invalid")))
    kind = request.headers.get("content-type", "")
    if field == "body" and kind and not kind.startswith("application/json"):
        message = f"the body must be a JSON object sent as Content-Type: application/json, not {kind[:100]}"
    return error_response(request, 422, ErrorInfo(type="validation_error", message=message, field=field))


async def _http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, HTTPException)
    type_ = getattr(exc, "type", _TYPE_BY_STATUS.get(exc.status_code, "error"))
    info = ErrorInfo(type=type_, message=str(exc.detail), field=getattr(exc, "field", None),
                     blocked=getattr(exc, "blocked", None))
    return error_response(request, exc.status_code, info, headers=dict(exc.headers or {}))


def _redis_down(retry_after_s: int) -> Any:
    """503 without the reason's text: redis-py names the address it could not reach, which no caller (with
    or without a key) should learn; the log keeps it."""

    async def handler(request: Request, exc: Exception) -> JSONResponse:
        log.warning("queue backend unreachable (request %s): %s", request_id(request), exc)
        info = ErrorInfo(type="unavailable", message="queue backend unreachable; retry later")
        return error_response(request, 503, info, headers={"Retry-After": str(retry_after_s)})

    return handler


def _redis_full(retry_after_s: int) -> Any:
    """The queue Redis reached its `maxmemory` (policy `noeviction`): it refuses writes rather than drop
    queued jobs or owed results, so new work waits until results expire."""

    async def handler(request: Request, exc: Exception) -> JSONResponse:
        info = ErrorInfo(type="unavailable", message="queue backend full; retry later")
        return error_response(request, 503, info, headers={"Retry-After": str(retry_after_s)})

    return handler


async def _check_pool_broken(request: Request, exc: Exception) -> JSONResponse:
    info = ErrorInfo(type="unavailable", message=str(exc))
    return error_response(request, 503, info, headers={"Retry-After": "1"})


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    # Starlette answers unhandled exceptions from its outermost middleware, outside RequestContext, so the
    # request id header is set here: a 500 is exactly the response whose id the client must be able to quote.
    info = ErrorInfo(type="internal", message="internal error; quote the request id when reporting it")
    return error_response(request, 500, info, headers={"X-Request-Id": request_id(request)})


def install(app: FastAPI, retry_after_s: int) -> None:
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(HTTPException, _http)
    for exc in (RedisConnectionError, RedisTimeoutError):
        app.add_exception_handler(exc, _redis_down(retry_after_s))
    app.add_exception_handler(OutOfMemoryError, _redis_full(retry_after_s))
    app.add_exception_handler(PoolBroken, _check_pool_broken)
    app.add_exception_handler(Exception, _internal)
