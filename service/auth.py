"""API keys: who is calling, as a tenant name, from `Authorization: Bearer <key>`.

Keys live in a JSON-lines file (`PRECOND_API_KEYS_FILE`), one record per key: its id, its tenant, the
SHA-256 of the key (never the key: keys are 256-bit random tokens, so a plain hash cannot be reversed or
brute-forced, and a lookup stays one dict access), when it was created, when it expires and whether it was
revoked. `precond keys create|list|revoke` manages the file; the gateway notices a change of the file at the
next request (one `stat`), so a revocation needs no restart.

Without a keys file the gateway is open: every caller is the tenant `public`. `precond serve` allows that
only on a loopback address, and `PRECOND_REQUIRE_AUTH` (set by docker-compose) refuses to start without keys.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import secrets
import tempfile
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from jobs.keys import tenant_tag
from service.errors import ServiceError

if TYPE_CHECKING:  # deps builds Services from a KeyStore: a runtime import would be circular
    from service.deps import Services
    from service.quotas import Refusal

log = logging.getLogger("precond.auth")
OPEN_TENANT = "public"
KEY_PREFIX = "pk_"
_bearer = HTTPBearer(auto_error=False, description="An API key made by `precond keys create`.")


@dataclass(frozen=True)
class KeyRecord:
    id: str
    tenant: str
    sha256: str
    created: str
    expires: str | None = None
    revoked: bool = False

    def expired(self, now: datetime) -> bool:
        return self.expires is not None and datetime.fromisoformat(self.expires) <= now


def digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> tuple[str, str]:
    """A fresh key and its public id (the id names it in `list` and `revoke`; only the key authenticates)."""
    key_id = "k_" + secrets.token_hex(6)
    return key_id, f"{KEY_PREFIX}{secrets.token_urlsafe(32)}"


def read_records(path: Path) -> list[KeyRecord]:
    records = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.strip():
            try:
                records.append(KeyRecord(**json.loads(line)))
            except (ValueError, TypeError) as exc:
                raise ValueError(f"{path}, line {number}: not a key record ({exc})") from exc
    return records


def write_records(path: Path, records: list[KeyRecord]) -> None:
    """Atomically, readable by its owner only: the file names tenants and holds key hashes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=".keys-")
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        out.writelines(json.dumps(asdict(r), sort_keys=True) + "\n" for r in records)
    os.chmod(temporary, 0o600)
    os.replace(temporary, path)


class KeyStore:
    """The keys file, re-read whenever it changes (size, mtime or inode)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._stamp: tuple[int, int, int] | None = None
        self._by_digest: dict[str, KeyRecord] = {}
        self.refresh()
        if not self.has_keys():
            log.warning("%s holds no usable key: every request will be refused (401)", path)

    def has_keys(self) -> bool:
        return any(not r.revoked for r in self._by_digest.values())

    def refresh(self) -> None:
        """Raises OSError/ValueError on the first read; later, a broken file keeps the last good keys."""
        stat = self.path.stat()
        stamp = (stat.st_size, stat.st_mtime_ns, stat.st_ino)
        if stamp == self._stamp:
            return
        try:
            records = read_records(self.path)
        except (OSError, ValueError):
            if self._stamp is None:
                raise
            log.exception("keys file %s unreadable; keeping the %d keys read before", self.path, len(self._by_digest))
            return
        self._by_digest = {r.sha256: r for r in records}
        self._stamp = stamp
        log.info("keys file %s: %d keys", self.path, len(records))

    def tenant(self, key: str) -> str:
        """The key's tenant, or a 401 that says what is wrong with the key."""
        try:
            self.refresh()
        except OSError:
            log.exception("keys file %s cannot be read; keeping the last keys", self.path)
        record = self._by_digest.get(digest(key))
        if record is None:
            raise unauthorized("unknown API key")
        if record.revoked:
            raise unauthorized(f"API key {record.id} was revoked")
        if record.expired(datetime.now(UTC)):
            raise unauthorized(f"API key {record.id} expired at {record.expires}")
        return record.tenant


def unauthorized(message: str) -> ServiceError:
    return ServiceError(401, message, "unauthorized", headers={"WWW-Authenticate": "Bearer"})


def _tenant_of(store: KeyStore, credentials: HTTPAuthorizationCredentials | None) -> str:
    if credentials is None or credentials.scheme.lower() != "bearer" or not credentials.credentials:
        raise unauthorized("missing API key: send the header 'Authorization: Bearer <key>'")
    return store.tenant(credentials.credentials)


def refuse(services: Services, tag: str, refusal: Refusal | None) -> None:
    """A 429 naming the limit (`rate_limited`, `jobs_limited`, `auth_limited`), counted under the tenant's tag."""
    if refusal is not None:
        services.metrics.rejections.labels(tag, refusal.limit).inc()
        raise ServiceError(429, refusal.message, f"{refusal.limit}_limited",
                           headers={"Retry-After": str(refusal.retry_after_s)})


async def authenticate(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
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
    tag = tenant_tag(services.secret, tenant)
    request.state.tenant, request.state.tenant_tag = tenant, tag  # metrics show the tag, never the name
    refuse(services, tag, await services.quotas.take_request(tag, tenant))
    return tenant


Tenant = Annotated[str, Depends(authenticate)]
