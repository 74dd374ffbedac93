"""Finished results under their job id, which is a hash of the normalised request and the model identity.

Kept apart from arq's own result keys on purpose: arq's results expire with `result_ttl_s` and also record
cancellations and crashes, while this cache holds successes only and lives `cache_ttl_s` (days). A hit is
answered by the gateway alone; no worker sees it.

It lives in the cache Redis (`PRECOND_CACHE_REDIS_URL`), which may evict under memory pressure
(`allkeys-lru`): an evicted entry is a miss, and the job simply runs again.

Every entry is signed: `v1.<hex HMAC-SHA256>.<result JSON>`, the HMAC keyed by the deployment secret
(`PRECOND_SECRET`) over the cache key and the JSON. Whoever can write to the cache Redis but does not hold
the secret cannot make the gateway answer with a result no worker computed: `get` treats an entry without a
valid signature as a miss, deletes it and logs a warning.

A gateway also keeps the entries it read last, verified, in its own memory (`recent_bytes`, a minute at most):
a repeated request is then answered without a round trip to Redis, which was a tenth of the gateway's CPU per
cache hit. A result never changes under its key (the key is a digest of the request), so a kept entry can only
outlive an entry Redis evicted or an operator deleted, and for at most `RECENT_TTL_S`.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
from typing import Any, Final

from cachetools import TTLCache
from redis.asyncio import Redis

from precond.jobs.queue.keys import cache_key

log = logging.getLogger("precond.cache")

VERSION: Final = b"v1"
_DOMAIN: Final = b"precond-result-cache-v1\x00"
RECENT_TTL_S: Final = 60
"""How long a gateway answers from an entry it keeps without reading Redis again."""
RECENT_ENTRY_BYTES: Final = 64 * 1024
"""Larger results are read from Redis each time: the memory is for the many small answers of a guard."""
RECENT_ENTRY_OVERHEAD: Final = 256
"""Bytes counted per kept entry besides its payload (its key and the cache's bookkeeping), so that the bound
holds for tiny results too."""


def signature(secret: bytes, key: str, payload: bytes) -> bytes:
    """Hex HMAC-SHA256 of an entry: the key is covered, so a valid entry cannot be replayed under another."""
    message = _DOMAIN + key.encode() + b"\x00" + payload
    return hmac.new(secret, message, hashlib.sha256).hexdigest().encode()


def seal(secret: bytes, key: str, payload: bytes) -> bytes:
    """The stored form of `payload` under `key`."""
    return b".".join((VERSION, signature(secret, key, payload), payload))


def unseal(secret: bytes, key: str, raw: bytes) -> bytes | None:
    """The payload of a stored entry, or None when it is not one this deployment signed."""
    version, _, rest = raw.partition(b".")
    mac, _, payload = rest.partition(b".")
    if version != VERSION or not hmac.compare_digest(mac, signature(secret, key, payload)):
        return None
    return payload


def _kept_size(payload: bytes) -> int:
    return len(payload) + RECENT_ENTRY_OVERHEAD


class ResultCache:
    def __init__(self, redis: Redis[bytes], ttl_s: int, secret: bytes, recent_bytes: int = 0) -> None:
        """`recent_bytes`: how much of what `get` read to keep in this process (0: none; a worker only writes)."""
        if not secret:
            raise ValueError("the result cache needs the deployment secret")
        self.redis = redis
        self.ttl_s = ttl_s
        self._secret = secret
        self._recent: TTLCache[str, bytes] | None = (
            TTLCache(recent_bytes, min(ttl_s, RECENT_TTL_S), getsizeof=_kept_size) if recent_bytes else None
        )

    async def get(self, job_id: str) -> dict[str, Any] | None:
        key = cache_key(job_id)
        payload = None if self._recent is None else self._recent.get(key)
        if payload is None:
            payload = await self._read(key)
            if payload is None:
                return None
            if self._recent is not None and len(payload) <= RECENT_ENTRY_BYTES:
                self._recent[key] = payload
        return dict(json.loads(payload))

    async def _read(self, key: str) -> bytes | None:
        raw = await self.redis.get(key)
        if raw is None:
            return None
        payload = unseal(self._secret, key, raw)
        if payload is None:
            log.warning("cache entry %s is not signed by this deployment: ignored and deleted", key)
            await self.redis.delete(key)
        return payload

    async def put(self, job_id: str, result: dict[str, Any]) -> None:
        key = cache_key(job_id)
        await self.redis.set(key, seal(self._secret, key, json.dumps(result).encode()), ex=self.ttl_s)
