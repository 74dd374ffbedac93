"""The check route's short way in: a check-actions request handed to its endpoint without FastAPI's request
handler, and a check whose answer is cached found by its body's digest, per tenant.

A check is the gateway's most frequent request and nearly all of its cost is the gateway's own. FastAPI's
request handler (solving the endpoint's dependencies, then parsing and validating its body and query) was a
quarter of the gateway's CPU per check under py-spy; here the same steps are taken in the same order by
direct calls: the key and the tenant's rate first (`auth.bearer`, the route's own dependency), then the
body parsed as Starlette parses it and validated by the request's model. Anything out of the ordinary (a
query other than one plain `wait`, a body that is not JSON or not valid, a content type FastAPI would not
read as JSON) goes to FastAPI's handler instead, which answers it as it always has: the caller already
worked out is handed over (`auth.authenticate`), so no token is taken and no failure counted twice.

A check that took the queue and was answered from the result cache is then answered the next time its exact
body comes from the same tenant without parsing, validating, rendering or screening it again: the digest of
the body leads to the job id and cache key it became (`CheckMemo`), the result cache is asked as before, and
the answer is the one `submit_job` gives for a cached result. What the digest skips is a function of the body
and the tenant alone (never of a stored set, whose latest version may change: such a body is never kept), and
what a result cache no longer holds is answered the long way.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Final

from fastapi import Request, Response
from pydantic import ValidationError

from precond.gateway.caller import Caller
from precond_client.schemas import CheckRequest

MEMO_PER_TENANT: Final = 512
"""Check bodies a gateway process remembers per tenant (the least recently used goes first): some 200 bytes
each. Each tenant has its own, so that no tenant's requests push out another's (which the other could time)."""

_WAIT = re.compile(rb"^(?:wait=(\d{1,6}(?:\.\d{1,6})?))?$")
"""The query strings answered here: none, or one plain `wait` (FastAPI's handler checks any other)."""

_JSON_TYPES: Final = frozenset({"application/json", "application/json; charset=utf-8"})


@dataclass(frozen=True)
class Known:
    """What a check's body became: its job id and where its result is cached."""

    job_id: str
    cache_key: str


class CheckMemo:
    """Per tenant tag: the body digests of checks answered from the result cache, and what each became."""

    def __init__(self, per_tenant: int = MEMO_PER_TENANT) -> None:
        self.per_tenant = per_tenant
        self._tenants: dict[str, OrderedDict[bytes, Known]] = {}  # tenants are bounded by the keys file

    def get(self, tag: str, digest: bytes) -> Known | None:
        known = self._tenants.get(tag)
        found = None if known is None else known.get(digest)
        if found is not None and known is not None:
            known.move_to_end(digest)
        return found

    def put(self, tag: str, digest: bytes, found: Known) -> None:
        known = self._tenants.setdefault(tag, OrderedDict())
        known[digest] = found
        known.move_to_end(digest)
        while len(known) > self.per_tenant:
            known.popitem(last=False)


def digest(body: bytes) -> bytes:
    return hashlib.sha256(body).digest()


def plain_wait(query: bytes) -> tuple[bool, float | None]:
    """Whether the query is one this route reads itself, and its `wait` (None: not given)."""
    match = _WAIT.match(query)
    if match is None:
        return False, None
    return True, None if match.group(1) is None else float(match.group(1))


Endpoint = Callable[[CheckRequest, Request, Caller, float | None], Awaitable[Response]]
Cached = Callable[[Request, Caller, Known], Awaitable[Response | None]]


async def answer(request: Request, body: bytes, authenticate: Callable[[Request], Awaitable[Caller]],
                 cached: Cached, endpoint: Endpoint) -> Response | None:
    """The check's answer, or None where FastAPI's handler must answer it (the caller, once known, is kept on
    the request for that handler). Raises what the endpoint raises, as through FastAPI."""
    readable, wait = plain_wait(request.scope.get("query_string", b""))
    content_type = request.headers.get("content-type", "").lower()
    if not readable or not body or content_type not in _JSON_TYPES:
        return None
    caller = await authenticate(request)
    known = request.app.state.services.check_memo.get(caller.tag, digest(body))
    if known is not None:
        response = await cached(request, caller, known)
        if response is not None:
            return response
    try:
        check = CheckRequest.model_validate(json.loads(body))
    except (ValueError, RecursionError, ValidationError):  # JSONDecodeError, UnicodeDecodeError: ValueErrors;
        return None  # deep nesting: RecursionError (FastAPI answers each its own way)
    return await endpoint(check, request, caller, wait)
