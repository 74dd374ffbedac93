"""Commands to Redis packed by hiredis (C) in the asyncio client too, as redis-py's synchronous client does.

redis-py 5's asyncio connection packs every command in Python, argument by argument: ~30 µs for one of the
worker's take and finish scripts (15-20 arguments each) against ~4 µs for hiredis, on every command of the
guard's hot path. The packer used is redis-py's own
`HiredisRespSerializer`; it writes the same bytes (the multi-word command names split, `repr` of numbers,
UTF-8 text) and refuses the same values (a `bool`, an object) with `DataError` (tests/jobs/test_redis_packing.py).
"""

from __future__ import annotations

from redis.asyncio.connection import AbstractConnection
from redis.connection import HiredisRespSerializer  # type: ignore[attr-defined]  # types-redis predates it
from redis.typing import EncodableT

_SERIALIZER = HiredisRespSerializer()


def _pack_command(self: AbstractConnection, *args: EncodableT) -> list[bytes]:
    packed: list[bytes] = _SERIALIZER.pack(*args)
    return packed


def pack_with_hiredis() -> None:
    """From now on in this process, asyncio connections pack their commands with hiredis (idempotent)."""
    AbstractConnection.pack_command = _pack_command  # type: ignore[method-assign]
