"""Who is calling: the tenant of the key in `Authorization: Bearer <key>` (precond/gateway/api_keys.py), worked out
once per request as a `Caller`, with the request-rate and failed-authentication limits taken on the way.

Without a keys file the gateway is open: every caller is the tenant `public`. `precond serve` allows that
only on a loopback address, and `PRECOND_REQUIRE_AUTH` (set by docker-compose) refuses to start without keys.
`public` is held to the tenants' request rate unless `PRECOND_PUBLIC_RATE_LIMIT` is off (`serve --no-rate-limit`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from precond.gateway.api_keys import KeyStore, unauthorized
from precond.gateway.caller import Caller
from precond.gateway.errors import ServiceError
from precond.jobs.queue.keys import tenant_tag
from precond_client.schemas import ErrorResponse

if TYPE_CHECKING:
    from precond.gateway.deps import Services
    from precond.gateway.quotas import Refusal

OPEN_TENANT = "public"


def _tenant_of(store: KeyStore, credentials: HTTPAuthorizationCredentials | None) -> str:
    if credentials is None or credentials.scheme.lower() != "bearer" or not credentials.credentials:
        raise unauthorized("missing API key: send the header 'Authorization: Bearer <key>'")
    return store.tenant(credentials.credentials)


def refuse(services: Services, tag: str, refusal: Refusal | None) -> None:
    """Raise `refusal_error` when there is a refusal."""
    if refusal is not None:
        raise refusal_error(services, tag, refusal)


def refusal_error(services: Services, tag: str, refusal: Refusal) -> ServiceError:
    """A 429 naming the limit (`rate_limited`, `jobs_limited`, `auth_limited`), counted under the tenant's tag."""
    services.metrics.rejections.labels(tag, refusal.limit).inc()
    return ServiceError(429, refusal.message, f"{refusal.limit}_limited",
                        headers={"Retry-After": str(refusal.retry_after_s)})


async def authenticate(request: Request, credentials: HTTPAuthorizationCredentials | None) -> Caller:
    """The caller's tenant: from its key when keys are configured, else the one open tenant. Every route that
    needs a key takes a token of its tenant's request rate here; a source address that failed to authenticate
    too often is refused before its key is looked at (the source is the TCP peer: behind a reverse proxy, let
    uvicorn take it from X-Forwarded-For with `--forwarded-allow-ips`)."""
    services: Services = request.app.state.services
    if services.keys is None:
        tenant = OPEN_TENANT
    else:
        source = request.client.host if request.client is not None else "-"
        refuse(services, "-", services.quotas.auth_blocked(source))
        try:
            tenant = _tenant_of(services.keys, credentials)
        except ServiceError:
            refuse(services, "-", await services.quotas.auth_failed(source))
            raise
    caller = Caller(tenant, tenant_tag(services.secret, tenant))
    request.state.tenant_tag = caller.tag  # metrics show the tag, never the name
    if services.keys is not None or services.settings.public_rate_limit:
        refuse(services, caller.tag, await services.quotas.take_request(caller))
    return caller


class ApiKeyBearer(HTTPBearer):
    """The key's header as the API's security scheme (OpenAPI) and the caller it names, in one dependency: a
    `Depends` of its own for the header cost every keyed request another level of FastAPI's dependency
    solving."""

    async def __call__(self, request: Request) -> Caller:  # type: ignore[override]  # as FastAPI's HTTPBasic
        """The caller, worked out once per request: a route that authenticated before handing the request to
        FastAPI's handler (`fast_check`) left it on the request, its token taken and its failures counted."""
        known = getattr(request.state, "caller", None)
        if isinstance(known, Caller):
            return known
        caller = await authenticate(request, await super().__call__(request))
        request.state.caller = caller
        return caller


bearer = ApiKeyBearer(auto_error=False, scheme_name="HTTPBearer",
                      description="An API key made by `precond keys create`.")
CurrentCaller = Annotated[Caller, Depends(bearer)]

RATE_LIMITED: dict[str, Any] = {
    "model": ErrorResponse,
    "description": "The tenant's request rate (`rate_limited`), or too many failed authentications from this "
    "address (`auth_limited`); see Retry-After.",
}
"""The 429 every route that takes a `CurrentCaller` may answer (its OpenAPI entry)."""
