"""A pooled asyncio Redis connection handed out without a read when nothing is left unread on it.

Before every command redis-py 5 makes sure that the connection it takes from its pool holds no stale reply and
was not closed by the server: it reads from it under a zero timeout (`can_read_destructive`). That read sees
only what the event loop has already received (its cancellation is scheduled before the loop's next look at
the socket), yet costs every command a turn of the loop, a cancelled read and a caught `TimeoutError`: 20-35 µs of the
150-270 µs of CPU a command took on the 2-core machine, and the gateway and the worker send three commands
each per check. What it would find is readable without reading: bytes received sit in the
connection's stream buffer or in hiredis' reader, and a connection the server closed has its stream at EOF
or in error. A connection with none of these is handed out at once; any other goes through redis-py's own
check (data or EOF found: disconnected and connected afresh), and so does every connection whose parser is
not hiredis' (`tests/jobs/test_redis_checkout.py`).
"""

from __future__ import annotations

from typing import Any

from redis.asyncio.connection import AbstractConnection, ConnectionPool

from precond import patches

_POOL: Any = ConnectionPool  # types-redis predates `ensure_connection`
_checked_by_redis_py: Any = getattr(_POOL, "ensure_connection", None)
_HIREDIS_PARSER = ("redis._parsers.hiredis", "_AsyncHiredisParser")


def nothing_unread(connection: AbstractConnection) -> bool:
    """Connected, with hiredis' parser, no byte received and not yet read, no EOF and no error."""
    parser: Any = getattr(connection, "_parser", None)
    stream: Any = getattr(connection, "_reader", None)
    return (
        type(parser).__name__ == _HIREDIS_PARSER[1]
        and connection.is_connected
        and parser._connected
        and parser._reader is not None
        and not parser._reader.has_data()
        and not stream._buffer
        and not stream._eof
        and stream.exception() is None
    )


async def _ensure_connection(self: Any, connection: AbstractConnection) -> None:
    if not nothing_unread(connection):
        await _checked_by_redis_py(self, connection)


def _needs() -> list[str]:
    """What the patch replaces (the pool's check-out check) and reads: the connection's parser and stream, the
    hiredis parser's reader and state, the stream's buffer and EOF."""
    connection = ("redis.asyncio.connection", "AbstractConnection")
    return (patches.missing("redis.asyncio.connection", "ConnectionPool", "ensure_connection")
            + patches.missing(*connection, "_parser", "is_connected")
            + patches.unassigned(*connection, "__init__", "_reader")
            + patches.unassigned(*_HIREDIS_PARSER, "__init__", "_reader")
            + patches.unassigned(*_HIREDIS_PARSER, "on_connect", "_connected")
            + patches.missing("hiredis", "Reader", "has_data")
            + patches.unassigned("asyncio", "StreamReader", "__init__", "_buffer", "_eof")
            + patches.missing("asyncio", "StreamReader", "exception"))


def check_out_without_read() -> bool:
    """From now on in this process, pools hand out connections with nothing unread at once (idempotent); False,
    and a log line, where this redis-py lacks what the patch replaces."""

    def install() -> None:
        _POOL.ensure_connection = _ensure_connection

    return patches.apply("connections checked out without a read", _needs(), install)
