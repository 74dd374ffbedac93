"""Trained policies (LoRA adapters) as the gateway and the workers share them, in the queue Redis (which never
evicts): a worker stores what it trained, the gateway lists, reads and deletes, a worker reads the weights of
the version a next action names. Like precondition sets, keys carry the tenant's tag, so another tenant's
adapter is simply not there; versions are never rewritten.

    precond:policies:<tenant tag>         Redis set of the tenant's adapter ids (its size is the per-tenant bound)
    precond:policy-bytes:<tenant tag>     bytes of all the tenant's stored versions (bounded per tenant)
    precond:policy:<tenant tag>:<id>      hash: `latest` → n; `<n>` → version n's `PolicyAdapter` JSON;
                                          `<n>:weights` → its adapter_model.safetensors; `<n>:job` → the job
                                          that stored it (a retried job finds its own version, not a conflict)
"""

from __future__ import annotations

import re
from typing import Any, Final

from precond.jobs.queue.keys import PREFIX
from precond_client.schemas.api import ADAPTER_REFERENCE
from precond_client.schemas.training import PolicyAdapter

STORE_SCRIPT: Final = """
local n = tonumber(ARGV[1])
local latest = tonumber(redis.call('hget', KEYS[2], 'latest') or '0')
if latest >= n and redis.call('hget', KEYS[2], ARGV[1] .. ':job') == ARGV[7] then return n end
if n == 1 then
  if latest ~= 0 then return -2 end
  if redis.call('scard', KEYS[1]) >= tonumber(ARGV[2]) then return -3 end
else
  if latest == 0 then return -1 end
  if latest ~= n - 1 then return -2 end
  if n > tonumber(ARGV[3]) then return -5 end
end
local size = #ARGV[4] + #ARGV[5]
if tonumber(redis.call('get', KEYS[3]) or '0') + size > tonumber(ARGV[6]) then return -4 end
redis.call('sadd', KEYS[1], ARGV[8])
redis.call('hset', KEYS[2], 'latest', n, ARGV[1], ARGV[4], ARGV[1] .. ':weights', ARGV[5], ARGV[1] .. ':job', ARGV[7])
redis.call('incrby', KEYS[3], size)
return n
"""
"""Store version n (1: a new adapter, counted against the tenant's bound of adapters; n > 1: only if n-1 is
still the latest and n is within the bound of versions) if the tenant's stored bytes stay within its bound."""

DELETE_SCRIPT: Final = """
local latest = tonumber(redis.call('hget', KEYS[2], 'latest') or '0')
if latest == 0 then return 0 end
local size = 0
for n = 1, latest do
  size = size + redis.call('hstrlen', KEYS[2], tostring(n)) + redis.call('hstrlen', KEYS[2], n .. ':weights')
end
redis.call('del', KEYS[2])
redis.call('srem', KEYS[1], ARGV[1])
redis.call('decrby', KEYS[3], size)
return 1
"""
"""Delete an adapter with all its versions, giving their bytes back to the tenant's bound."""

MISSING: Final = -1
CONFLICT: Final = -2
TOO_MANY_ADAPTERS: Final = -3
TENANT_BYTES_FULL: Final = -4
TOO_MANY_VERSIONS: Final = -5

_REFERENCE = re.compile(ADAPTER_REFERENCE)


def index_key(tag: str) -> str:
    return f"{PREFIX}:policies:{tag}"


def adapter_key(tag: str, adapter_id: str) -> str:
    return f"{PREFIX}:policy:{tag}:{adapter_id}"


def bytes_key(tag: str) -> str:
    return f"{PREFIX}:policy-bytes:{tag}"


def parse_reference(reference: str) -> tuple[str, int | None] | None:
    """`id@version` or `id` (latest); None for anything else."""
    match = _REFERENCE.match(reference)
    if match is None:
        return None
    return match.group(1), int(match.group(2)) if match.group(2) else None


async def store(redis: Any, tag: str, adapter: PolicyAdapter, weights: bytes, job_id: str, max_adapters: int,
                max_versions: int, max_tenant_bytes: int) -> int:
    """The version stored (a retried job's own earlier store counts), or one of the codes above."""
    keys = (index_key(tag), adapter_key(tag, adapter.id), bytes_key(tag))
    return int(await redis.eval(STORE_SCRIPT, 3, *keys, adapter.version, max_adapters, max_versions,
                                adapter.model_dump_json(), weights, max_tenant_bytes, job_id, adapter.id))


async def latest(redis: Any, tag: str, adapter_id: str) -> int | None:
    found = await redis.hget(adapter_key(tag, adapter_id), "latest")
    return int(found) if found is not None else None


async def get(redis: Any, tag: str, reference: str) -> PolicyAdapter | None:
    """The version a reference names (its latest for a bare id), if it is this tenant's."""
    parsed = parse_reference(reference)
    if parsed is None:
        return None
    adapter_id, version = parsed
    version = version or await latest(redis, tag, adapter_id)
    if version is None:
        return None
    found = await redis.hget(adapter_key(tag, adapter_id), str(version))
    return PolicyAdapter.model_validate_json(found) if found is not None else None


async def weights(redis: Any, tag: str, adapter: PolicyAdapter) -> bytes | None:
    found: bytes | None = await redis.hget(adapter_key(tag, adapter.id), f"{adapter.version}:weights")
    return found


async def listed(redis: Any, tag: str) -> tuple[list[PolicyAdapter], int]:
    """The latest version of each of the tenant's adapters (newest first) and the bytes they all take."""
    found = []
    for member in await redis.smembers(index_key(tag)):
        adapter = await get(redis, tag, member.decode() if isinstance(member, bytes) else member)
        if adapter is not None:
            found.append(adapter)
    used = await redis.get(bytes_key(tag))
    return sorted(found, key=lambda a: a.created, reverse=True), int(used or 0)


async def delete(redis: Any, tag: str, adapter_id: str) -> bool:
    keys = (index_key(tag), adapter_key(tag, adapter_id), bytes_key(tag))
    return bool(await redis.eval(DELETE_SCRIPT, 3, *keys, adapter_id))
