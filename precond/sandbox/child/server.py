"""The fork server: started by the worker as ``python -I -S`` with an empty environment; never runs
untrusted code itself.

Per request it hands the request to a fresh, already confined child, enforces the call's wall clock and
each unit's CPU and wall budget, and forwards the result under the request's id. When a child dies or is
killed inside a unit (one candidate, one proposed call), that unit alone fails with its reason and a new
child continues with the units that remain, so one runaway part never costs the rest of the call.

A request that names a scope (the worker's tenant tag: a check on the guard's hot path) may be answered by a
warm child of that scope, one that already answered a request of it and kept what it compiled. A warm child
serves one scope only and is confined like every other; between requests it is stopped (SIGSTOP: whatever its
untrusted code left behind cannot use a CPU while it waits); it is used only while it is small and far from
its CPU limit, and any failure on it is re-run on a fresh child with a whole wall clock of its own, so what a
call may use does not depend on the calls before it. What a scope's code changes in the modules it imports
stays for that scope's next calls on the same child (its own state, never another scope's): an answer that
must depend on its request alone is asked without a scope.
"""

from __future__ import annotations

import collections
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
WARM_PER_SERVER = 4
"""Warm children one server keeps (least recently used first out): one per scope."""
WARM_MAX_USES = 500
"""Calls a warm child answers before it is retired (its compiled code and its heap start afresh)."""
WARM_MAX_RESIDENT_MB = 64
"""A child that grew past this keeps no memory of the machine's after its request: it is not kept warm."""
WARM_STALL_S = 1.0
"""How long a reused child may take to answer before the call is run again on a fresh one (a check answers in
milliseconds: more means it is stuck in what an earlier call of its scope left running)."""
WARM_CPU_SHARE = 0.5
"""A warm child is retired once it has used this share of its CPU limit, so every call on it has at least the
other half; a call that still runs out is re-run on a fresh child."""
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
    uses: int = 0


@dataclasses.dataclass
class Outcome:
    """How one child's run ended: `end` holds its final result; otherwise `kind` says why not, and
    `unit` is the unit that was running (to be blamed) if any."""

    kind: str  # "end" | "timeout" | "died" | "unit-cpu" | "unit-wall" | "malformed" | "result"
    phase: str
    end: dict[str, typing.Any] | None = None
    unit: int | None = None
    detail: str = ""


def _limit_error(result: dict[str, typing.Any]) -> bool:
    """An end that reports a limit or an internal error: on a reused child, possibly its past calls' doing."""
    error = result.get("error")
    return isinstance(error, dict) and error.get("kind") in ("limit", "internal")


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
        self.warm: collections.OrderedDict[str, Child] = collections.OrderedDict()

    # ------------------------------------------------------------------------------------ lifecycle

    def serve_forever(self) -> None:
        spare = self.fork_child()
        try:
            for line in self.requests:
                header = json.loads(line)
                body = self.requests.read(int(header["size"]))
                scope = header.get("scope") if isinstance(header.get("scope"), str) else None
                answer = self.call_warm(scope, body) if scope is not None else None
                spare_used = answer is None
                # a fresh child's wall clock starts when it does: never what a warm child left of it
                reply, payload, last = answer or self.call(spare, body, self.deadline(), keep=scope is not None)
                reply["id"] = header["id"]
                self.send(reply, payload)
                # teardown and the next fork happen after the answer, off its latency
                self.keep_or_discard(scope, last, reply)
                if spare_used:
                    spare = self.fork_child()
        finally:
            self.discard(spare)  # idempotent: a spare that was used is already discarded or warm (below)
            for child in self.warm.values():
                self.discard(child)
            shutil.rmtree(self.workdir, ignore_errors=True)

    def deadline(self) -> float:
        """The wall clock of one run of a request, from now."""
        return time.monotonic() + float(self.limits["timeout_s"])

    def call_warm(self, scope: str, body: bytes) -> tuple[dict[str, object], bytes, Child] | None:
        """The reply of this scope's warm child, or None when there is none or it failed (the call is then
        run again on a fresh child: a warm child's failure may be its past calls', never this call's)."""
        child = self.warm.pop(scope, None)
        if child is None:
            return None
        try:
            os.kill(child.pid, signal.SIGCONT)
        except OSError:
            self.discard(child)
            return None
        reply, payload, last = self.call(child, body, self.deadline(), keep=True, retry=True)
        if reply.get("status") == "ok" and last is child:
            return reply, payload, last
        self.discard(last)
        return None

    def keep_or_discard(self, scope: str | None, child: Child, reply: dict[str, object]) -> None:
        child.uses += 1
        if scope is None or reply.get("status") != "ok" or not self.fit_to_keep(child):
            self.discard(child)
            return
        try:
            os.kill(child.pid, signal.SIGSTOP)  # idle means stopped: what its calls left running cannot run on
        except OSError:
            self.discard(child)
            return
        self.warm[scope] = child
        while len(self.warm) > WARM_PER_SERVER:
            self.discard(self.warm.popitem(last=False)[1])

    def fit_to_keep(self, child: Child) -> bool:
        if child.status is not None or child.request < 0 or child.uses >= WARM_MAX_USES:
            return False
        if cpu_seconds(child.pid) >= WARM_CPU_SHARE * float(self.limits["cpu_s"]):
            return False
        try:
            with open(f"/proc/{child.pid}/statm", "rb") as statm:
                resident_pages = int(statm.read().split()[1])
        except (OSError, ValueError, IndexError):
            return False  # cannot tell how large it is: not kept
        return resident_pages * os.sysconf("SC_PAGE_SIZE") <= WARM_MAX_RESIDENT_MB << 20

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

    def call(self, first: Child, body: bytes, deadline: float, keep: bool = False,
             retry: bool = False) -> tuple[dict[str, object], bytes, Child]:
        """The reply to one request, and the last child used (still to be discarded or kept). `keep`: the
        first child stays for the scope's next request if this one ends well; `retry`: any failure of the
        first child (a reused one) is answered `{"status": "retry"}` instead of being blamed on the call."""
        units: dict[int, dict[str, typing.Any]] = {}
        child, failures = first, 0
        while True:
            # a reused child that says nothing at once is stuck in what its past calls left: the call moves on
            stall = time.monotonic() + WARM_STALL_S if retry else None
            outcome = self.run(child, body, units, deadline, keep=keep and failures == 0, stall=stall)
            if outcome.kind == "end" and outcome.end is not None and not (retry and _limit_error(outcome.end)):
                payload = json.dumps({"result": outcome.end, "units": {str(k): v for k, v in units.items()}})
                return {"status": "ok", "size": len(payload)}, payload.encode("ascii"), child
            if retry:
                return {"status": "retry"}, b"", child
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

    def run(self, child: Child, body: bytes, units: dict[int, dict[str, typing.Any]], deadline: float,
            keep: bool = False, stall: float | None = None) -> Outcome:
        header = json.dumps({"skip": sorted(units), "size": len(body), "keep": keep}).encode("ascii") + b"\n"
        try:
            write_all(child.request, header + body)
        except OSError:
            keep = False  # it is gone: what it says (nothing) is collected below
        if not keep:
            os.close(child.request)
            child.request = -1
        pidfd = os.pidfd_open(child.pid)
        try:
            return self.collect(child, pidfd, units, deadline, stall)
        finally:
            os.close(pidfd)

    def collect(self, child: Child, pidfd: int, units: dict[int, dict[str, typing.Any]],
                deadline: float, stall: float | None = None) -> Outcome:
        """How the child's run ends; `stall`: when it must have said something (a reused child), or the run ends
        as `timeout`."""
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
            if received == 0 and stall is not None:
                if now >= stall:
                    return Outcome("timeout", phase, unit=unit)
                wait = min(wait, stall - now)
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
        if outcome.kind == "timeout":  # `unit`: which part was running, so the caller can tell it from the rest
            return {"status": "limit", "limit": "timeout", "unit": outcome.unit,
                    "message": f"no result within {self.limits['timeout_s']} s (SANDBOX_TIMEOUT_S){where}"}
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
        if code == BOUNDARY_FAILED and self.was_root:
            return ("the seccomp filter or a resource limit could not be installed, or root could not be given up "
                    "(children of a root worker drop to nobody, which needs CAP_SETUID and CAP_SETGID; a non-root "
                    "worker needs no capability)")
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
