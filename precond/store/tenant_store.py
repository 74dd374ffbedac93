"""A tenant's stored records as numbered, never rewritten versions in the queue Redis (which never evicts): the
one store behind precondition sets and trained policies (LoRA adapters). Keys carry the tenant, so another
tenant's record is simply not there: the same "not found" as a record that never existed, without any lookup of
owners. Each tenant is bounded in records, versions per record and bytes, checked and written in one script.

    precond:<kind.index>:<tenant>         Redis set of the tenant's record ids (its size is the per-tenant bound)
    precond:<kind.size>:<tenant>          bytes of all the tenant's stored versions (bounded per tenant)
    precond:<kind.record>:<tenant>:<id>   hash: `latest` → n; `<n>` → version n (JSON); `<n>:<part>` → a further
                                          part of version n counted in its bytes (an adapter's `weights`);
                                          `<n>:job` → the job that stored it (a retried job finds its own
                                          version, not a conflict); and fields the kind keeps beside them,
                                          uncounted (a set's `created` and `summary`, rewritten with each version)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from precond.jobs.queue.keys import PREFIX
from precond.jobs.scripts import LuaScript


@dataclass(frozen=True)
class Kind:
    """One kind of record: its key names, and the parts of a version counted in its bytes besides its JSON."""

    index: str
    size: str
    record: str
    parts: tuple[str, ...] = ()

    def index_key(self, tenant: str) -> str:
        return f"{PREFIX}:{self.index}:{tenant}"

    def size_key(self, tenant: str) -> str:
        return f"{PREFIX}:{self.size}:{tenant}"

    def record_key(self, tenant: str, record_id: str) -> str:
        return f"{PREFIX}:{self.record}:{tenant}:{record_id}"

    def keys(self, tenant: str, record_id: str) -> list[str]:
        return [self.index_key(tenant), self.record_key(tenant, record_id), self.size_key(tenant)]


SETS: Final = Kind("sets", "set-bytes", "set")
POLICIES: Final = Kind("policies", "policy-bytes", "policy", parts=("weights",))

MISSING: Final = -1
"""A version n > 1 of a record that does not exist (deleted meanwhile, or never this tenant's)."""
CONFLICT: Final = -2
"""Version n - 1 is no longer the latest (or, for n = 1, the id is taken)."""
TOO_MANY_RECORDS: Final = -3
TOO_MANY_BYTES: Final = -4
TOO_MANY_VERSIONS: Final = -5

_PUT = LuaScript("""
local n = tonumber(ARGV[2])
local latest = tonumber(redis.call('hget', KEYS[2], 'latest') or '0')
if ARGV[6] ~= '' and latest >= n and redis.call('hget', KEYS[2], ARGV[2] .. ':job') == ARGV[6] then return n end
if n == 1 then
  if latest ~= 0 then return -2 end
  if redis.call('scard', KEYS[1]) >= tonumber(ARGV[3]) then return -3 end
else
  if latest == 0 then return -1 end
  if latest ~= n - 1 then return -2 end
  if n > tonumber(ARGV[4]) then return -5 end
end
local size = #ARGV[7]
local fields = {'latest', n, ARGV[2], ARGV[7]}
local parts_end = 8 + 2 * tonumber(ARGV[8])
for i = 9, parts_end, 2 do
  size = size + #ARGV[i + 1]
  fields[#fields + 1] = ARGV[2] .. ':' .. ARGV[i]
  fields[#fields + 1] = ARGV[i + 1]
end
for i = parts_end + 1, #ARGV, 2 do
  fields[#fields + 1] = ARGV[i]
  fields[#fields + 1] = ARGV[i + 1]
end
local bound = tonumber(ARGV[5])
if bound > 0 and tonumber(redis.call('get', KEYS[3]) or '0') + size > bound then return -4 end
if ARGV[6] ~= '' then
  fields[#fields + 1] = ARGV[2] .. ':job'
  fields[#fields + 1] = ARGV[6]
end
redis.call('sadd', KEYS[1], ARGV[1])
redis.call('hset', KEYS[2], unpack(fields))
redis.call('incrby', KEYS[3], size)
return n
""")
"""Store version n (1: a new record, counted against the tenant's bound of records; n > 1: only if n-1 is still
the latest and n is within the bound of versions) if the tenant's stored bytes stay within its bound (0: none)."""

_DELETE = LuaScript("""
local latest = tonumber(redis.call('hget', KEYS[2], 'latest') or '0')
if latest == 0 then return 0 end
local size = 0
for n = 1, latest do
  size = size + redis.call('hstrlen', KEYS[2], tostring(n))
  for i = 2, #ARGV do
    size = size + redis.call('hstrlen', KEYS[2], n .. ':' .. ARGV[i])
  end
end
redis.call('del', KEYS[2])
redis.call('srem', KEYS[1], ARGV[1])
redis.call('decrby', KEYS[3], size)
return 1
""")
"""Delete a record with all its versions, giving their bytes back to the tenant's bound."""


@dataclass(frozen=True)
class Bounds:
    """A tenant's bounds for one kind; `tenant_bytes` 0: unbounded."""

    records: int
    versions: int
    tenant_bytes: int


async def put(redis: Any, kind: Kind, tenant: str, record_id: str, version: int, record: str | bytes,
              bounds: Bounds, *, job: str = "", parts: Mapping[str, str | bytes] | None = None,
              beside: Mapping[str, str | bytes] | None = None) -> int:
    """Store `record` (and its counted `parts`) as version `version` of the tenant's record, and the `beside`
    fields with it: the version stored (a retried `job`'s own earlier store counts), or one of the codes above."""
    parts, beside = dict(parts or {}), dict(beside or {})
    unknown = set(parts) - set(kind.parts)
    if unknown:
        raise ValueError(f"{kind.record} records have no part {sorted(unknown)}")
    args: list[Any] = [record_id, version, bounds.records, bounds.versions, bounds.tenant_bytes, job, record,
                       len(parts)]
    for name, value in [*parts.items(), *beside.items()]:
        args += [name, value]
    return int(await _PUT(redis, kind.keys(tenant, record_id), args))


async def latest(redis: Any, kind: Kind, tenant: str, record_id: str) -> int | None:
    found = await redis.hget(kind.record_key(tenant, record_id), "latest")
    return int(found) if found is not None else None


async def read(redis: Any, kind: Kind, tenant: str, record_id: str, version: int, part: str = "") -> bytes | None:
    """Version `version` of the record (its JSON, or its counted `part`), if the tenant has it."""
    found: bytes | None = await redis.hget(kind.record_key(tenant, record_id),
                                           f"{version}:{part}" if part else str(version))
    return found


async def ids(redis: Any, kind: Kind, tenant: str) -> list[str]:
    """The tenant's record ids, sorted."""
    members = await redis.smembers(kind.index_key(tenant))
    return sorted(m.decode() if isinstance(m, bytes) else m for m in members)


async def count(redis: Any, kind: Kind, tenant: str) -> int:
    return int(await redis.scard(kind.index_key(tenant)))


async def used_bytes(redis: Any, kind: Kind, tenant: str) -> int:
    return int(await redis.get(kind.size_key(tenant)) or 0)


async def delete(redis: Any, kind: Kind, tenant: str, record_id: str) -> bool:
    return bool(await _DELETE(redis, kind.keys(tenant, record_id), [record_id, *kind.parts]))
