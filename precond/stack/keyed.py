"""A real stack whose API needs keys, one per tenant: for the client, the CLI's `--server` and the walkthrough."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from precond.gateway.api_keys import KeyRecord, digest, new_key, read_records, write_records
from precond.stack.local import Stack, make_stack, serving


@dataclass
class KeyedStack:
    stack: Stack
    keys: dict[str, str]
    """Tenant → its API key."""

    @property
    def url(self) -> str:
        return self.stack.base_url


def make_key(path: Path, tenant: str) -> str:
    """A new key of `tenant` appended to the keys file (as `precond keys create` does); the key itself."""
    key_id, key = new_key()
    record = KeyRecord(key_id, tenant, digest(key), datetime.now(UTC).isoformat())
    write_records(path, [*(read_records(path) if path.exists() else []), record])
    return key


@contextmanager
def keyed_stack(
    tmp: Path, model_dir: Path, tenants: tuple[str, ...], workers: int = 1, **settings: str
) -> Iterator[KeyedStack]:
    """Redis, the gateway with a keys file holding one key per tenant, and `workers` workers, for the block."""
    keys_file = tmp / "keys.jsonl"
    keys = {tenant: make_key(keys_file, tenant) for tenant in tenants}
    stack = make_stack(tmp, model_dir, PRECOND_API_KEYS_FILE=str(keys_file), **settings)
    with serving(stack, workers=workers):
        yield KeyedStack(stack, keys)
