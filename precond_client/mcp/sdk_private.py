"""The MCP SDK's private helpers the proxy's own `tools/call` path reuses, so that it checks a result and stops a
process exactly as the SDK's session does; imported here only, and checked when imported. What a helper reads of
its argument is private too: `stop_piped_process` hands `_stop_server_process` a process shaped as it reads one.

They are not the SDK's public API: the extra bounds the SDK to the minor version they were read in
(`SDK_CHECKED`), and a version that lacks one stops `precond mcp` at import with an error naming the helper and
the installed version (never a silently different check). tests/client/test_mcp_sdk_private.py checks what each
one does.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import version
from signal import Signals
from typing import Any

from anyio.abc import Process

SDK_CHECKED = "2.3"
"""The `mcp` minor version these helpers were read in (pyproject's `mcp>=2.3,<2.4`)."""

try:
    from mcp.client.session import _clamp_inbound_ttl as clamp_inbound_ttl
    from mcp.client.session import _later_revision_fields as later_revision_fields
    from mcp.client.stdio import _stop_server_process as stop_server_process
except ImportError as error:  # pragma: no cover - only on an SDK outside the extra's bounds
    raise ImportError(
        f"precond mcp reuses private helpers of the MCP SDK read in mcp {SDK_CHECKED}.x; the installed mcp "
        f"{version('mcp')} lacks one ({error}): install the extra's bounds (pip install 'precond-client[mcp]')"
    ) from error



class _Closing:
    """A pipe as `stop_server_process` closes one (`aclose`), closed by a callback of its owner."""

    def __init__(self, close: Callable[[], None]) -> None:
        self.close = close

    async def aclose(self) -> None:
        self.close()


class _Piped(Process):
    """A process started on the caller's own pipes, as `stop_server_process` reads a process: an anyio `Process`
    (it asserts so) whose `stdin` and `stdout` it closes, whose pid and return code it reads and whose group it
    signals; the rest is the process's."""

    def __init__(self, process: Process, close_stdin: Callable[[], None], close_stdout: Callable[[], None]) -> None:
        self.process = process
        self.pipes = (_Closing(close_stdin), _Closing(close_stdout))

    async def aclose(self) -> None:
        await self.process.aclose()

    async def wait(self) -> int:
        return await self.process.wait()

    def terminate(self) -> None:
        self.process.terminate()

    def kill(self) -> None:
        self.process.kill()

    def send_signal(self, signal: Signals) -> None:
        self.process.send_signal(signal)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def returncode(self) -> int | None:
        return self.process.returncode

    @property
    def stdin(self) -> Any:
        return self.pipes[0]

    @property
    def stdout(self) -> Any:
        return self.pipes[1]

    @property
    def stderr(self) -> Any:
        return self.process.stderr


async def stop_piped_process(process: Process, close_stdin: Callable[[], None],
                             close_stdout: Callable[[], None]) -> None:
    """`stop_server_process` for a process whose stdin and stdout are the caller's own pipes (closed with the
    callbacks, stdin first): its end of input, a grace period, then its whole process group ended."""
    await stop_server_process(_Piped(process, close_stdin, close_stdout))


__all__ = ["SDK_CHECKED", "clamp_inbound_ttl", "later_revision_fields", "stop_piped_process", "stop_server_process"]
