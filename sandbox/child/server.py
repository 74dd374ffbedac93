"""The fork server: started by the worker as ``python -I -S`` with an empty environment; never runs
untrusted code itself.

Per request it hands the request to a fresh, already confined child, enforces the call's wall clock and
each unit's CPU and wall budget, and forwards the result under the request's id. When a child dies or is
killed inside a unit (one candidate, one proposed call), that unit alone fails with its reason and a new
child continues with the units that remain, so one runaway part never costs the rest of the call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import os
import select
import shutil
import signal
import sys
import tempfile
import time
import typing

from .boundary import confine, harden_server
from .entry import BOUNDARY_FAILED, run_child
from .framing import CHUNK, split_frames, write_all
from .values import clean

SPARE_FD = 900
UNIT_WALL_FACTOR = 3.0
PROBE_DENIED = 0
PROBE_ALLOWED = 1


@dataclasses.dataclass
class Child:
    """A forked, already confined child waiting for its one request (fork cost stays off the latency)."""

    pid: int
    request: int
    result: int
    status: int | None = None
    cpu_s: float = 0.0


@dataclasses.dataclass
class Outcome:
    """How one child's run ended: `end` holds its final result; otherwise `kind` says why not, and
    `unit` is the unit that was running (to be blamed) if any."""

    kind: str  # "end" | "timeout" | "died" | "unit-cpu" | "unit-wall" | "malformed" | "result"
    phase: str
    end: dict[str, typing.Any] | None = None
    unit: int | None = None
    detail: str = ""


def cpu_seconds(pid: int) -> float:
    """CPU time of another process through its POSIX CPU clock (no /proc, works on non-dumpable ones)."""
    try:
        return time.clock_gettime(((~pid) << 3) | 2)
    except OSError:
        return 0.0


class Server:
    def __init__(self, requests: typing.BinaryIO, responses: int, config: dict[str, typing.Any],
                 bpf: bytes | None) -> None:
        self.requests, self.responses, self.config, self.bpf = requests, responses, config, bpf
        self.limits = config["limits"]
        self.was_root = os.geteuid() == 0
        self.pid = os.getpid()
        self.workdir = tempfile.mkdtemp(prefix="sandbox-")
        os.chmod(self.workdir, 0o555)

    # ------------------------------------------------------------------------------------ lifecycle

    def serve_forever(self) -> None:
        spare = self.fork_child()
        try:
            for line in self.requests:
                header = json.loads(line)
                body = self.requests.read(int(header["size"]))
                reply, payload, last = self.call(spare, body)
                reply["id"] = header["id"]
                self.send(reply, payload)
                self.discard(last)  # teardown and the next fork happen after the answer, off its latency
                spare = self.fork_child()
        finally:
            self.discard(spare)
            shutil.rmtree(self.workdir, ignore_errors=True)

    def send(self, header: dict[str, object], payload: bytes = b"") -> None:
        data = json.dumps(header).encode("ascii") + b"\n"
        if header.get("status") == "ok":
            data += payload + b"\n"
        write_all(self.responses, data)

    def fork_child(self) -> Child:
        request_read, request_write = os.pipe()
        result_read, result_write = os.pipe()
        pid = os.fork()
        if pid == 0:
            try:
                os.dup2(request_read, SPARE_FD)  # via high numbers: the pipes may themselves sit on 3 or 4
                os.dup2(result_write, SPARE_FD + 1)
                os.dup2(SPARE_FD, 3)
                os.dup2(SPARE_FD + 1, 4)
                run_child(self.config, self.workdir, self.was_root, self.bpf)
            finally:
                os._exit(70)
        os.close(request_read)
        os.close(result_write)
        return Child(pid, request_write, result_read)

    def discard(self, child: Child) -> None:
        """Kill (if still running), reap and close: nothing of the child outlives its request. Idempotent."""
        if child.status is None:
            try:
                os.killpg(child.pid, signal.SIGKILL)
            except OSError:
                os.kill(child.pid, signal.SIGKILL)
            self.reap(child)
        for fd in (child.request, child.result):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        child.request = child.result = -1

    @staticmethod
    def reap(child: Child) -> None:
        _, status, usage = os.wait4(child.pid, 0)
        child.status, child.cpu_s = status, usage.ru_utime + usage.ru_stime

    # ------------------------------------------------------------------------------------- one call

    def call(self, first: Child, body: bytes) -> tuple[dict[str, object], bytes, Child]:
        """The reply to one request, and the last child used (still to be discarded)."""
        units: dict[int, dict[str, typing.Any]] = {}
        deadline = time.monotonic() + float(self.limits["timeout_s"])
        child, failures = first, 0
        while True:
            outcome = self.run(child, body, units, deadline)
            if outcome.kind == "end" and outcome.end is not None:
                payload = json.dumps({"result": outcome.end, "units": {str(k): v for k, v in units.items()}})
                return {"status": "ok", "size": len(payload)}, payload.encode("ascii"), child
            self.discard(child)  # reaped: its exit status says what killed it
            blame = self.blame(outcome, child)
            if outcome.unit is None or blame is None:
                return self.failure(outcome, child), b"", child
            units[outcome.unit] = {"failed": blame}
            failures += 1
            if failures > int(self.limits["max_failed_units"]) or time.monotonic() >= deadline:
                limit = "timeout" if time.monotonic() >= deadline else "cpu"
                message = f"{failures} parts of this call exceeded their limits; the last: {blame}"
                return {"status": "limit", "limit": limit, "message": message}, b"", child
            child = self.fork_child()

    def run(self, child: Child, body: bytes, units: dict[int, dict[str, typing.Any]], deadline: float) -> Outcome:
        skip = json.dumps({"skip": sorted(units)}).encode("ascii") + b"\n"
        with contextlib.suppress(OSError):
            write_all(child.request, skip + body)
        os.close(child.request)
        child.request = -1
        pidfd = os.pidfd_open(child.pid)
        try:
            return self.collect(child, pidfd, units, deadline)
        finally:
            os.close(pidfd)

    def collect(self, child: Child, pidfd: int, units: dict[int, dict[str, typing.Any]],
                deadline: float) -> Outcome:
        cap = int(self.limits["result_bytes"])
        unit_cpu = float(self.limits["unit_cpu_s"])
        buffer, received, eof = bytearray(), 0, False
        phase, unit, last = "starting", None, max(units, default=-1)
        cpu0 = wall0 = 0.0
        while True:
            try:
                for frame in split_frames(buffer, cap):
                    kind = frame.get("t")
                    if kind == "end" and isinstance(frame.get("result"), dict) and unit is None:
                        return Outcome("end", phase, end=frame["result"])
                    index = frame.get("unit")
                    if kind == "phase":
                        phase = clean(str(frame.get("where")), 200)
                    elif kind == "begin" and unit is None and isinstance(index, int) and index > last:
                        unit, last, phase = index, index, clean(str(frame.get("where")), 200)
                        cpu0, wall0 = cpu_seconds(child.pid), time.monotonic()
                    elif kind == "unit" and isinstance(index, int) and isinstance(frame.get("result"), dict) and (
                            index == unit or (unit is None and index > last)):
                        units[index], unit, last = frame["result"], None, index
                    else:
                        raise ValueError("frame out of order")
            except ValueError as exc:
                return Outcome("malformed", phase, unit=unit, detail=clean(str(exc), 100))
            if eof and child.status is not None:
                return Outcome("died", phase, unit=unit)
            now = time.monotonic()
            wait = deadline - now
            if unit is not None:
                spent = cpu_seconds(child.pid) - cpu0
                if spent >= unit_cpu:
                    return Outcome("unit-cpu", phase, unit=unit, detail=f"{spent:.1f} s of CPU")
                if now - wall0 >= unit_cpu * UNIT_WALL_FACTOR:
                    return Outcome("unit-wall", phase, unit=unit, detail=f"{now - wall0:.1f} s")
                wait = min(wait, unit_cpu - spent, wall0 + unit_cpu * UNIT_WALL_FACTOR - now)
            if deadline - now <= 0:
                return Outcome("timeout", phase, unit=unit)
            watched = ([] if eof else [child.result]) + ([] if child.status is not None else [pidfd])
            ready = select.select(watched, [], [], max(wait, 0.001))[0]
            if child.result in ready:
                data = os.read(child.result, CHUNK)
                eof = not data
                buffer += data
                received += len(data)
                if received > cap + 1024:
                    return Outcome("result", phase, unit=unit)
            if pidfd in ready:
                self.reap(child)

    def blame(self, outcome: Outcome, child: Child) -> str | None:
        """Why the running unit failed, when the failure is that unit's own; None when it is the call's."""
        if outcome.kind == "unit-cpu":
            return f"cpu limit exceeded: {outcome.detail} (limit {self.limits['unit_cpu_s']} s per part)"
        if outcome.kind == "unit-wall":
            return f"time limit exceeded: no answer in {outcome.detail}"
        if outcome.kind == "malformed":
            return f"broke the sandbox protocol ({outcome.detail})"
        if outcome.kind == "died" and child.status is not None:
            if os.WIFSIGNALED(child.status):
                return f"the process running it died (signal {os.WTERMSIG(child.status)})"
            if os.waitstatus_to_exitcode(child.status) != BOUNDARY_FAILED:
                return "the process running it exited without an answer"
        return None

    def failure(self, outcome: Outcome, child: Child) -> dict[str, object]:
        where = f" while running {outcome.phase}"
        if outcome.kind == "timeout":
            return {"status": "limit", "limit": "timeout",
                    "message": f"no result within {self.limits['timeout_s']} s{where}"}
        if outcome.kind == "result":
            return {"status": "limit", "limit": "result", "message": "result too large"}
        status = child.status
        if status is not None and os.WIFSIGNALED(status):
            sig = os.WTERMSIG(status)
            if sig == signal.SIGXCPU or (sig == signal.SIGKILL and child.cpu_s >= float(self.limits["cpu_s"])):
                return {"status": "limit", "limit": "cpu", "message": f"used {child.cpu_s:.1f} s of CPU{where}"}
            return {"status": "crash", "message": f"child killed by signal {sig}{where}"}
        if status is not None and os.waitstatus_to_exitcode(status) == BOUNDARY_FAILED:
            return {"status": "unconfined", "message": "the sandbox could not confine its child; nothing ran"}
        return {"status": "crash", "message": f"child ended without a result{where}"}

    # -------------------------------------------------------------------------------------- probing

    def probe(self) -> str | None:
        """Fork one child, confine it and try what the boundary forbids: None when all of it was refused."""
        pid = os.fork()
        if pid == 0:
            try:
                confine(self.limits, self.workdir, self.was_root, self.bpf)
            except BaseException:
                os._exit(BOUNDARY_FAILED)
            code = PROBE_DENIED
            for attempt in (lambda: os.open("/", os.O_RDONLY), lambda: os.kill(self.pid, 0), os.fork):
                try:
                    attempt()
                    code = PROBE_ALLOWED
                except OSError:
                    pass
            os._exit(code)
        _, status = os.waitpid(pid, 0)
        code = os.waitstatus_to_exitcode(status)
        if self.bpf is None:
            return "unconfined development mode: no seccomp filter"
        if code == PROBE_DENIED:
            return None
        if code == BOUNDARY_FAILED:
            return "the seccomp filter or a resource limit could not be installed"
        return "a confined child could still open files, signal or fork"


def main() -> None:
    request_fd, response_fd = int(sys.argv[1]), int(sys.argv[2])
    config = json.loads(sys.argv[3])
    bpf = bytes.fromhex(config["seccomp"]) if config.get("seccomp") else None
    for name in sorted(set(config["allowed_imports"]) | {"unicodedata"}):
        __import__(name)  # loaded before any child is confined: a confined child cannot open a module file
    namespace = harden_server()
    server = Server(os.fdopen(request_fd, "rb"), response_fd, config, bpf)
    unconfined = server.probe()
    server.send({"status": "hello", "confined": unconfined is None, "reason": unconfined,
                 "network_namespace": namespace is None, "detail": namespace})
    gc.collect()
    gc.freeze()  # children share the server's pages copy-on-write; the collector would touch them all
    server.serve_forever()
