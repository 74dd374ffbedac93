"""The review page for precondition sets (`/ui/`): one static HTML page and its ES modules, served as files.

The page holds no data and runs no code of the service's: it calls the JSON API with the key the reviewer
types in (kept in the tab's sessionStorage, sent as a Bearer header, never in a URL), so every read and edit
goes through the API's own checks, tenancy and limits. That is why these routes need no key: a browser
navigation cannot carry one, and there is nothing here to protect. They are left out of the OpenAPI document
and take a token from the same rate limiter as the API, keyed by the caller's address.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Final

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from precond.gateway.caller import Caller
from precond.gateway.deps import ServicesDep
from precond.gateway.errors import ServiceError
from precond.gateway.set_store import parse_reference
from precond.jobs.queue import keys

PAGE_DIR: Final = Path(__file__).resolve().parents[1] / "ui"
ASSET: Final = re.compile(r"^[a-z]+\.(js|css)$")
MEDIA: Final = {"js": "text/javascript; charset=utf-8", "css": "text/css; charset=utf-8"}
HEADERS: Final = {
    # the page renders tenants' programs and rules: never as markup (textContent only), and even a slip could
    # run nothing that is not the page's own script, nor send anything anywhere but this origin
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


async def _rate_limited(request: Request, services: ServicesDep) -> None:
    """The API's token bucket (PRECOND_TENANT_RATE_PER_S, PRECOND_TENANT_BURST), per caller address."""
    source = f"ui {request.client.host if request.client else '-'}"
    refusal = await services.quotas.take_request(Caller(source, keys.tenant_tag(services.secret, source)))
    if refusal is not None:
        services.metrics.rejections.labels("-", refusal.limit).inc()
        raise ServiceError(429, refusal.message, f"{refusal.limit}_limited",
                           headers={"Retry-After": str(refusal.retry_after_s)})


router = APIRouter(prefix="/ui", include_in_schema=False, dependencies=[Depends(_rate_limited)])


def _file(name: str) -> str:
    return (PAGE_DIR / name).read_text(encoding="utf-8")


def _page(status: int = 200) -> HTMLResponse:
    """The one page; the script reads the status from `data-status` (a script cannot see its page's status)."""
    html = _file("index.html").replace("<body>", f'<body data-status="{status}">', 1)
    return HTMLResponse(html, status_code=status, headers=HEADERS)


@router.get("", response_class=RedirectResponse)
async def ui_root() -> RedirectResponse:
    return RedirectResponse("/ui/", status_code=308)


@router.get("/", response_class=HTMLResponse)
async def sets_page() -> HTMLResponse:
    """The tenant's sets; the page asks for a key when the API answers 401."""
    return _page()


@router.get("/sets/{reference}", response_class=HTMLResponse)
async def set_page(reference: str) -> HTMLResponse:
    """One set (`id` or `id@n`). Whether it exists, and is the caller's, only the API can say (the page shows
    its 404); a reference that cannot name a set is a 404 page here."""
    try:
        parse_reference(reference)
    except ServiceError:
        return _page(404)
    return _page()


@router.get("/static/{name}")
async def asset(name: str) -> Response:
    """The page's own script and style: a fixed pattern of names in one directory, nothing else."""
    match = ASSET.match(name)
    if match is None or not (PAGE_DIR / name).is_file():
        return _page(404)
    return Response(_file(name), media_type=MEDIA[match.group(1)], headers=HEADERS)


@router.get("/{rest:path}", response_class=HTMLResponse)
async def unknown(rest: str) -> HTMLResponse:
    """Any other address under /ui/: the page, with a 404 status, says there is nothing there."""
    return _page(404)

