"""API keys: a JSON-lines file (`PRECOND_API_KEYS_FILE`), one record per key: its id, its tenant, the SHA-256
of the key (never the key: keys are 256-bit random tokens, so a plain hash cannot be reversed or
brute-forced, and a lookup stays one dict access), when it was created, when it expires and whether it was
revoked. `precond keys create|list|revoke` manages the file; the gateway notices a change of the file at the
next request (one `stat`), so a revocation needs no restart.
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

from precond.gateway.errors import ServiceError

log = logging.getLogger("precond.auth")
KEY_PREFIX = "pk_"


@dataclass(frozen=True)
class KeyRecord:
    id: str
    tenant: str
    sha256: str
    created: str
    expires: str | None = None
    revoked: bool = False
    operator: bool = False
    """An operator's key also reads what the open routes tell nobody else: why the service is not ready."""

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
        return self.record(key).tenant

    def record(self, key: str) -> KeyRecord:
        """The key's record if it is usable, else a 401 that says what is wrong with the key."""
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
        return record


def unauthorized(message: str) -> ServiceError:
    return ServiceError(401, message, "unauthorized", headers={"WWW-Authenticate": "Bearer"})
