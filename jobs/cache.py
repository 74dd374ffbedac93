"""Finished results under their job id, which is a hash of the normalised request and the model identity.

Kept apart from arq's own result keys on purpose: arq's results expire with `result_ttl_s` and also record
cancellations and crashes, while this cache holds successes only and lives `cache_ttl_s` (days). A hit is
answered by the gateway alone; no worker sees it.
"""

from __future__ import annotations

import json
from typing import Any

from redis.asyncio import Redis

from jobs.keys import cache_key


class ResultCache:
    def __init__(self, redis: Redis[bytes], ttl_s: int) -> None:
        self.redis = redis
        self.ttl_s = ttl_s

    async def get(self, job_id: str) -> dict[str, Any] | None:
        raw = await self.redis.get(cache_key(job_id))
        return None if raw is None else dict(json.loads(raw))

    async def put(self, job_id: str, result: dict[str, Any]) -> None:
        await self.redis.set(cache_key(job_id), json.dumps(result), ex=self.ttl_s)
