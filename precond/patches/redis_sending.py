"""A command written to a pooled asyncio Redis connection without a task when the socket takes it whole.

redis-py 5 writes every command under `asyncio.wait_for(write and drain, socket_timeout)`, and on Python
3.11 `wait_for` runs its coroutine as a new task: a task made and scheduled, a turn of the event loop, a timer
set and cancelled, for a write the kernel nearly always takes at once (a command is a few hundred bytes; a
socket's send buffer holds megabytes). 20-50 µs of CPU per command on the 2-core machine, and a check sends
five or six commands across the gateway and the worker.

The timeout is there for a write that cannot finish: a send buffer full because Redis stopped reading. Only
then has `drain` anything to wait for, so a command is written first and is done when the transport holds
none of it afterwards and is not closing; otherwise the connection is drained exactly as redis-py does, under
its socket timeout, with its disconnect and its errors (`tests/jobs/test_redis_sending.py`). Connections
that must connect first or check their health go through redis-py's own send.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from redis import exceptions
from redis.asyncio.connection import AbstractConnection

from precond import patches

_CONNECTION: Any = AbstractConnection  # the method is replaced on the class, as redis-py defines it
_sent_by_redis_py: Any = getattr(_CONNECTION, "send_packed_command", None)


async def _send_packed_command(
    self: Any, command: bytes | str | Iterable[bytes], check_health: bool = True
) -> None:
    writer = self._writer if self.is_connected else None
    if writer is None or (check_health and self.health_check_interval) or _unsent(writer):
        await _sent_by_redis_py(self, command, check_health)
        return
    if isinstance(command, str):
        command = command.encode()
    try:
        writer.writelines([command] if isinstance(command, bytes) else command)
    except BaseException as exc:  # as redis-py does: a command half written leaves the connection unusable
        await self.disconnect(nowait=True)
        if isinstance(exc, OSError):
            raise exceptions.ConnectionError(f"Error while writing to socket. {exc}") from exc
        raise
    if _unsent(writer):
        await _sent_by_redis_py(self, (), False)  # nothing more to write: drained under the socket timeout


def _unsent(writer: Any) -> bool:
    """Bytes the transport still holds, or a transport going away (whose drain raises the connection's error)."""
    return bool(writer.transport.get_write_buffer_size()) or writer.transport.is_closing()


def _needs() -> list[str]:
    """What the patch replaces and reads: the connection's send, writer, health-check interval, disconnect."""
    connection = ("redis.asyncio.connection", "AbstractConnection")
    return (patches.missing(*connection, "send_packed_command", "is_connected", "disconnect")
            + patches.unassigned(*connection, "__init__", "_writer", "health_check_interval"))


def send_without_task() -> bool:
    """From now on in this process, a command the socket takes whole is sent without a task (idempotent); False,
    and a log line, where this redis-py lacks what the patch replaces."""

    def install() -> None:
        _CONNECTION.send_packed_command = _send_packed_command

    return patches.apply("commands sent without a task", _needs(), install)
