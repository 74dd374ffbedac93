"""Who sent a request, worked out once by `service.auth.authenticate` and handed to every handler."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Caller:
    """The tenant behind a request.

    `name` appears only in messages to that tenant itself (its own limits); `tag`, the HMAC of the name under
    the deployment secret (`jobs.queue.keys.tenant_tag`), is what job ids, Redis keys and `/metrics` carry, so that
    none of them says who the tenants are.
    """

    name: str
    tag: str
