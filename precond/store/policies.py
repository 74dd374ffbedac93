"""Trained policies (LoRA adapters) as the gateway and the workers share them: a worker stores what it trained,
the gateway lists, reads and deletes, a worker reads the weights of the version a next action names. They are
kept by `precond.store.tenant_store` (kind `POLICIES`: `precond:policies:<tenant>`, `precond:policy:<tenant>:<id>`,
`precond:policy-bytes:<tenant>`), each version's `PolicyAdapter` JSON with its adapter_model.safetensors as the
counted part `weights`, like precondition sets: another tenant's adapter is simply not there.
"""

from __future__ import annotations

import re
from typing import Any

from precond.store import tenant_store
from precond.store.tenant_store import POLICIES
from precond_client.schemas import ADAPTER_REFERENCE
from precond_client.schemas.training import PolicyAdapter

_REFERENCE = re.compile(ADAPTER_REFERENCE)


def parse_reference(reference: str) -> tuple[str, int | None] | None:
    """`id@version` or `id` (latest); None for anything else."""
    match = _REFERENCE.match(reference)
    if match is None:
        return None
    return match.group(1), int(match.group(2)) if match.group(2) else None


async def store(redis: Any, tenant: str, adapter: PolicyAdapter, weights: bytes, job_id: str,
                bounds: tenant_store.Bounds) -> int:
    """The version stored (a retried job's own earlier store counts), or a `tenant_store` code."""
    return await tenant_store.put(redis, POLICIES, tenant, adapter.id, adapter.version, adapter.model_dump_json(),
                                  bounds, job=job_id, parts={"weights": weights})


async def get(redis: Any, tenant: str, reference: str) -> PolicyAdapter | None:
    """The version a reference names (its latest for a bare id), if it is this tenant's."""
    parsed = parse_reference(reference)
    if parsed is None:
        return None
    adapter_id, version = parsed
    version = version or await tenant_store.latest(redis, POLICIES, tenant, adapter_id)
    if version is None:
        return None
    found = await tenant_store.read(redis, POLICIES, tenant, adapter_id, version)
    return PolicyAdapter.model_validate_json(found) if found is not None else None


async def weights(redis: Any, tenant: str, adapter: PolicyAdapter) -> bytes | None:
    return await tenant_store.read(redis, POLICIES, tenant, adapter.id, adapter.version, "weights")


async def listed(redis: Any, tenant: str) -> tuple[list[PolicyAdapter], int]:
    """The latest version of each of the tenant's adapters (newest first) and the bytes they all take."""
    found = []
    for adapter_id in await tenant_store.ids(redis, POLICIES, tenant):
        adapter = await get(redis, tenant, adapter_id)
        if adapter is not None:
            found.append(adapter)
    return sorted(found, key=lambda a: a.created, reverse=True), await tenant_store.used_bytes(redis, POLICIES, tenant)
