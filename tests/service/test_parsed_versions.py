"""The gateway's parsed set versions: kept per tenant within a byte bound, so one tenant's sets never push
out another's."""

from __future__ import annotations

from precond.gateway.set_store import ParsedVersions
from precond_client.schemas import PreconditionSet


def version(set_id: str, number: int) -> PreconditionSet:
    return PreconditionSet(id=set_id, version=number, latest=number, reference=f"{set_id}@{number}",
                           created="2026-01-01T00:00:00+00:00", spec="class A:\n  pass\n", preconditions={})


def test_a_tenant_past_its_bytes_loses_its_own_oldest_version_only() -> None:
    cache = ParsedVersions(max_bytes_per_tenant=100)
    cache.put("other", "ps_o", 1, 60, version("ps_o", 1))
    for number in (1, 2, 3):
        cache.put("busy", "ps_b", number, 40, version("ps_b", number))
    assert cache.get("busy", "ps_b", 1) is None  # 3 x 40 > 100: the least recently used went
    assert cache.get("busy", "ps_b", 3) is not None and cache.get("busy", "ps_b", 2) is not None
    assert cache.get("other", "ps_o", 1) is not None  # untouched by the busy tenant


def test_a_version_is_found_only_under_its_tenant_and_number() -> None:
    cache = ParsedVersions()
    cache.put("a", "ps_x", 1, 10, version("ps_x", 1))
    assert cache.get("b", "ps_x", 1) is None and cache.get("a", "ps_x", 2) is None
    assert cache.get("a", "ps_x", 1) == version("ps_x", 1)


def test_a_version_over_the_bound_is_not_kept() -> None:
    cache = ParsedVersions(max_bytes_per_tenant=10)
    cache.put("a", "ps_x", 1, 11, version("ps_x", 1))
    assert cache.get("a", "ps_x", 1) is None
