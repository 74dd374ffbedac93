"""Commands to Redis packed by hiredis (C) in the asyncio client too, as redis-py's synchronous client does.

redis-py 5's asyncio connection packs every command in Python, argument by argument: ~30 µs for one of the
worker's take and finish scripts (15-20 arguments each) against ~4 µs for hiredis, on every command of the
guard's hot path. The packer used is redis-py's own
`HiredisRespSerializer`; it writes the same bytes (the multi-word command names split, `repr` of numbers,
UTF-8 text) and refuses the same values (a `bool`, an object) with `DataError` (tests/jobs/test_redis_packing.py).
"""

from __future__ import annotations

import importlib
from typing import Any

from redis.typing import EncodableT

from precond import patches


def _needs() -> list[str]:
    """What the patch replaces (the connection's `pack_command`) and uses (hiredis, redis-py's hiredis packer)."""
    absent = patches.missing("redis.asyncio.connection", "AbstractConnection", "pack_command")
    absent += patches.missing("redis.connection", "HiredisRespSerializer", "pack")
    return absent + patches.missing("hiredis", "pack_command")


def _install() -> None:
    serializer = importlib.import_module("redis.connection").HiredisRespSerializer()
    connection: Any = importlib.import_module("redis.asyncio.connection").AbstractConnection

    def pack_command(self: Any, *args: EncodableT) -> list[bytes]:
        packed: list[bytes] = serializer.pack(*args)
        return packed

    connection.pack_command = pack_command


def pack_with_hiredis() -> bool:
    """From now on in this process, asyncio connections pack their commands with hiredis (idempotent); False, and
    a log line, where this redis-py lacks what the patch replaces."""
    return patches.apply("commands packed by hiredis", _needs(), _install)
