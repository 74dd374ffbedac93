"""Warm fork servers (``sandbox.child.server``) and the pool that hands them to threads.

A server that does not answer in time, dies, or breaks the protocol is killed with its whole process
group and replaced; the caller gets SandboxCrashed. Only this module talks to server processes.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import secrets
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from precond.sandbox.types import SandboxCancelled, SandboxCrashed, SandboxError, SandboxUnavailable

log = logging.getLogger(__name__)

PACKAGE_DIR = Path(__file__).resolve().parent
PRECOND_DIR = PACKAGE_DIR.parent  # the `precond` package: `programs`, the stdlib-only program reader, lives there too
START_TIMEOUT_S = 30.0
READ_CHUNK = 1 << 16
"""As `sandbox.child.framing.CHUNK`: a pipe holds 64 KiB, and a larger read only costs a larger allocation."""
# `python -I -S`: no environment, no site-packages, no user paths. `precond` and `precond.sandbox` are
# registered as bare packages so that `precond.sandbox.child` and `precond.programs` load without the
# worker-side modules of `precond/sandbox/__init__.py`.
BOOTSTRAP = (
    "import sys, types\n"
    "for name, path in (('precond', sys.argv[1]), ('precond.sandbox', sys.argv[2])):\n"
    "    package = types.ModuleType(name)\n"
    "    package.__path__ = [path]\n"
    "    sys.modules[name] = package\n"
    "del sys.argv[1:3]\n"
    "from precond.sandbox.child.server import main\n"
    "main()\n"
)


CANCEL_POLL_S = 0.1
"""How often a call waiting on its server asks whether it was cancelled."""
RECENT_SCOPES = 4
"""Scopes a server is taken to hold warm children of: its last ones (the server keeps `WARM_PER_SERVER`, 4)."""


class ServerGone(Exception):
    """The server broke the protocol, died or missed its deadline; it must be replaced."""


class CallCancelled(Exception):
    """The caller cancelled while waiting; the server is mid-request and must be replaced."""


class ForkServer:
    """One server process and its two pipes. Not thread-safe: the pool lends it to one thread at a time."""

    def __init__(self, limits: Mapping[str, float | int], allowed_imports: Collection[str],
                 seccomp: bytes | None, allow_unconfined: bool) -> None:
        self._allow_unconfined = allow_unconfined
        request_read, self._request = os.pipe()
        self._response, response_write = os.pipe()
        config = json.dumps({"allowed_imports": sorted(allowed_imports), "limits": dict(limits),
                             "seccomp": seccomp.hex() if seccomp is not None else None})
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-I", "-S", "-c", BOOTSTRAP, str(PRECOND_DIR), str(PACKAGE_DIR),
                 str(request_read), str(response_write), config],
                pass_fds=(request_read, response_write), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                close_fds=True, env={}, cwd="/",
            )
        finally:
            os.close(request_read)
            os.close(response_write)
        self._buffer = bytearray()
        self._hello: dict[str, Any] | None = None
        self._cancelled: Callable[[], bool] | None = None
        self.scopes: collections.deque[str] = collections.deque(maxlen=RECENT_SCOPES)
        """The scopes of its last scoped calls that were answered, the latest last: where its warm children
        probably are. Only a hint for choosing a server; the server alone decides which child answers."""

    def ready(self) -> dict[str, Any]:
        """The server's hello, read once: whether its children are confined by the kernel policy."""
        if self._hello is None:
            hello = json.loads(self._read_line(time.monotonic() + START_TIMEOUT_S))
            if not isinstance(hello, dict) or hello.get("status") != "hello":
                raise ServerGone("fork server did not start")
            if not hello.get("confined"):
                reason = str(hello.get("reason"))
                if not self._allow_unconfined:
                    raise SandboxUnavailable(f"the kernel policy could not be set up: {reason}")
                log.error("SANDBOX UNCONFINED (development setting): untrusted code runs without the "
                          "kernel policy: %s", reason)
            self._hello = hello
        return self._hello

    def request(self, message: dict[str, Any], wait_s: float, cancelled: Callable[[], bool] | None = None,
                scope: str | None = None) -> tuple[dict[str, Any], bytes]:
        """Send one request; return the header and the raw result. A reply that does not carry this
        request's id is never taken as its answer. `cancelled` is polled while waiting (CallCancelled);
        `scope` lets a warm child of that scope, and only of it, answer (sandbox.child.server)."""
        self._cancelled = cancelled
        deadline = time.monotonic() + wait_s
        self.ready()
        call_id = secrets.token_hex(16)
        body = json.dumps(message, ensure_ascii=True).encode("ascii")
        header_line = json.dumps({"id": call_id, "size": len(body), "scope": scope}).encode("ascii") + b"\n"
        self._write(header_line + body, deadline)
        header = json.loads(self._read_line(deadline))
        if not isinstance(header, dict) or header.get("id") != call_id:
            raise ServerGone("reply does not answer this request")
        if header.get("status") != "ok":
            return header, b""
        size = int(header["size"])
        payload = self._read_exact(size + 1, deadline)
        if scope is not None:
            with suppress(ValueError):
                self.scopes.remove(scope)
            self.scopes.append(scope)
        return header, payload[:size]

    def shutdown(self, wait_s: float = 2.0) -> None:
        """EOF on its request pipe lets the server kill its waiting child and remove its directory."""
        with suppress(OSError):
            os.close(self._request)
        with suppress(subprocess.TimeoutExpired):
            self.process.wait(wait_s)
        self.kill()

    def kill(self) -> None:
        with suppress(OSError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        for fd in (self._request, self._response):
            with suppress(OSError):
                os.close(fd)

    def _write(self, data: bytes, deadline: float) -> None:
        view = memoryview(data)
        while view:
            self._wait(self._request, deadline, write=True)
            try:
                view = view[os.write(self._request, view):]
            except OSError as exc:
                raise ServerGone(f"request pipe: {exc}") from exc

    def _read_line(self, deadline: float) -> bytes:
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                line = bytes(self._buffer[:end])
                del self._buffer[: end + 1]
                return line
            self._fill(deadline)

    def _read_exact(self, size: int, deadline: float) -> bytes:
        while len(self._buffer) < size:
            self._fill(deadline)
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data

    def _fill(self, deadline: float) -> None:
        self._wait(self._response, deadline, write=False)
        data = os.read(self._response, READ_CHUNK)
        if not data:
            raise ServerGone("fork server closed its pipe")
        self._buffer += data

    def _wait(self, fd: int, deadline: float, write: bool) -> None:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ServerGone("fork server missed its deadline")
            if self._cancelled is not None and self._cancelled():
                raise CallCancelled()
            step = remaining if self._cancelled is None else min(remaining, CANCEL_POLL_S)
            watched = [fd]
            ready = select.select([], watched, [], step)[1] if write else select.select(watched, [], [], step)[0]
            if ready:
                return


class ServerPool:
    """N warm servers; a thread borrows one per call, so N calls run at once.

    A scoped call borrows the idle server that answered its scope most recently, where that scope's warm child
    waits; a call of a scope no idle server knows takes the idle server with the fewest scopes, so that the
    servers' warm children spread over the scopes; among equals the most recently used server (its memory is
    still in the CPU's caches). Taken in turn instead, every server kept a warm child of every busy scope and
    each child ran one call in N.
    """

    def __init__(self, size: int, limits: Mapping[str, float | int], allowed_imports: Collection[str],
                 seccomp: bytes | None, allow_unconfined: bool) -> None:
        if size < 1:
            raise ValueError("workers must be at least 1")
        self._limits = dict(limits)
        self._allowed = frozenset(allowed_imports)
        self._seccomp, self._allow_unconfined = seccomp, allow_unconfined
        self._idle: list[ForkServer] = []  # the most recently used last
        self._returned = threading.Condition()
        self._all: set[ForkServer] = set()
        self._lock = threading.Lock()
        self._closed = False
        for _ in range(size):
            self._idle.append(self._start())
        try:
            hellos = [server.ready() for server in self._all]  # every server checks its own children
            self.hello = hellos[0]
        except BaseException:
            self.close()
            raise

    def _start(self) -> ForkServer:
        server = ForkServer(self._limits, self._allowed, self._seccomp, self._allow_unconfined)
        with self._lock:
            self._all.add(server)
        log.debug("started fork server pid %d", server.process.pid)
        return server

    def _discard(self, server: ForkServer) -> None:
        server.kill()
        with self._lock:
            self._all.discard(server)

    def _borrow(self, scope: str | None) -> ForkServer:
        with self._returned:
            while not self._idle:
                self._returned.wait()
            return self._idle.pop(_choice(self._idle, scope))

    def _give_back(self, server: ForkServer) -> None:
        with self._returned:
            self._idle.append(server)
            self._returned.notify()

    @contextmanager
    def server(self, scope: str | None = None) -> Iterator[ForkServer]:
        """Lend a server (for `scope`: see the class); a server that failed is replaced rather than returned."""
        if self._closed:
            raise SandboxError("sandbox is closed")
        server = self._borrow(scope)
        try:
            yield server
        except ServerGone as exc:
            log.warning("fork server pid %d replaced: %s", server.process.pid, exc)
            self._discard(server)
            server = self._start()
            raise SandboxCrashed(str(exc)) from None
        except CallCancelled:
            self._discard(server)  # kills the server's process group: the running child goes with it
            server = self._start()
            raise SandboxCancelled("cancelled") from None
        except BaseException:
            self._discard(server)
            server = self._start()
            raise
        finally:
            if self._closed:
                server.shutdown()
            else:
                self._give_back(server)

    def call(self, message: dict[str, Any], wait_s: float, cancelled: Callable[[], bool] | None = None,
             scope: str | None = None) -> tuple[dict[str, Any], bytes]:
        with self.server(scope) as server:
            try:
                return server.request(message, wait_s, cancelled, scope)
            except (OSError, ValueError, KeyError) as exc:
                raise ServerGone(f"protocol error: {exc}") from exc

    def close(self) -> None:
        self._closed = True
        with self._lock:
            servers = list(self._all)
            self._all.clear()
        for server in servers:
            server.shutdown()


def _choice(idle: list[ForkServer], scope: str | None) -> int:
    """The index in `idle` (the most recently used last) of the server a call of `scope` borrows."""
    if scope is not None:
        for index in range(len(idle) - 1, -1, -1):
            if scope in idle[index].scopes:
                return index
    fewest = min(len(server.scopes) for server in idle)
    return max(index for index, server in enumerate(idle) if len(server.scopes) == fewest)
