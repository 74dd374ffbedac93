"""Attacks on a tenant's warm sandbox child (`precond.sandbox.child.server`), from the tenant's own spec.

Run by test_warm.py in-process and, as a separate program, under another (non-root) uid: it prints one JSON
object with what each attack saw. Kept as a plain script so the same attacks run unchanged in both
deployments (as root the children drop to `nobody`; as a non-root user they keep its uid).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from typing import Any

from precond.sandbox import LimitExceeded, Limits, Sandbox

# The spec counts, in a module every child shares with the server's import, how often `mark` ran in this
# process: a fresh child always sees 1 after the history below, a reused one more. (The rule reads the count
# from the object: a plain rule, judged in the call's first child, the one a scope's warm child can answer.)
COUNTING_SPEC = """
import collections

class Room:
    def mark(self):
        collections.marks = getattr(collections, 'marks', 0) + 1
        self.marks = collections.marks
    def enter(self):
        pass
"""
HISTORY = "room = Room()\nroom.mark()\n"
FIRST_TIME = {"Room.enter": ["self.marks == 1"]}
SCOPES = ["tenant-a", "tenant-a", "tenant-b", None, None, "tenant-b", "tenant-a"]
"""The calls of `scope_sequence`; a fresh child answers True, tenant-a's and tenant-b's warm ones False."""
EXPECTED = [True, False, True, True, True, False, False]

# After its request, the child collects its garbage before it waits for the next one; this spec replaces that
# collection, in the module every child shares, with an endless loop: a warm child that ran it would spin on a
# core while it waits (taking it from every tenant), and would never read its next request.
SPINS_WHEN_IDLE = """
import typing

class Room:
    def mark(self):
        typing.sys.modules['gc'].collect = lambda *args: [0 for _ in iter(int, 1)]
    def enter(self):
        pass
"""

# From its second call on, the warm child loops in the proposed call (its past left it that way).
SLOW_AFTER_FIRST = """
import collections

class Room:
    def mark(self):
        collections.marks = getattr(collections, 'marks', 0) + 1
    def enter(self):
        while collections.marks > 1:
            pass
"""
# A history that replaces the child's verdict function: in its own call, and in every later call its warm child
# answers, every proposed call reads "allowed". Its tenant's own state (docs/security.md); a result computed there
# is a function of what the tenant ran before, never of the request alone.
FORGING_SPEC = "import typing\nclass Door:\n    def open(self):\n        pass\n"
FORGING_HISTORY = ("typing.sys.modules['precond.sandbox.child.check']._verdict = "
                   "lambda *a: {'allowed': True, 'violations': [], 'error': None}\ndoor = Door()\n")
DOOR_SPEC = "class Door:\n    def lock(self):\n        self.locked = True\n    def open(self):\n        pass\n"
LOCKED = {"Door.open": ["not self.locked"]}
LOCKED_HISTORY = "door = Door()\ndoor.lock()\n"

# From its second call on, the warm child writes one byte of a frame and then waits: it has said something, so
# it is not "stalled", and it never ends. The call must still get a whole deadline on a fresh child.
HANGS_AFTER_A_BYTE = """
import collections
import typing

class Room:
    def mark(self):
        collections.marks = getattr(collections, 'marks', 0) + 1
        if collections.marks > 1:
            typing.sys.modules['os'].write(4, b'{')
            typing.sys.modules['time'].sleep(60)
    def enter(self):
        pass
"""
LIMITS = Limits(timeout_s=3.0, cpu_s=2, memory_mb=512, output_bytes=100_000, recursion=200)
UNIT_LIMITS = Limits(timeout_s=20, cpu_s=20, unit_cpu_s=0.5)


def scope_sequence(sandbox: Sandbox) -> list[bool]:
    """Whether each call of `SCOPES` was allowed: False means it ran where an earlier call had run."""
    out = []
    for scope in SCOPES:
        (verdict,) = sandbox.check(COUNTING_SPEC, FIRST_TIME, HISTORY, ["room.enter()"], scope)
        out.append(verdict.allowed and verdict.error is None)
    return out


def idle_spin(sandbox: Sandbox) -> dict[str, Any]:
    """CPU the warm child used in the second after its answer, and how the next call of its tenant went."""
    def check() -> bool:
        (verdict,) = sandbox.check(SPINS_WHEN_IDLE, {}, HISTORY, ["room.enter()"], "tenant-a")
        return verdict.allowed and verdict.error is None

    first = check()
    servers = _servers()
    before = _children_cpu_s(servers)
    time.sleep(1.0)
    idle = _children_cpu_s(servers) - before
    started = time.monotonic()
    second = check()
    return {"first": first, "idle_cpu_s": idle, "second": second, "second_s": time.monotonic() - started}


def unfit_child(sandbox: Sandbox) -> list[bool]:
    """Three calls of one tenant whose warm child loops from the second call on: each should answer as a
    first call does (allowed), the stuck part re-run on a fresh child."""
    out = []
    for _ in range(3):
        (verdict,) = sandbox.check(SLOW_AFTER_FIRST, {}, HISTORY, ["room.enter()"], "tenant-a")
        out.append(verdict.allowed and verdict.error is None)
    return out


def forged_then_unwarmed(sandbox: Sandbox) -> list[bool]:
    """Whether a locked door may be opened: on the tenant's warm child after its history forged the verdicts
    (allowed: its own state), then for the same tenant with `warm=False` (a fresh child: refused), as a result
    that is shared between tenants is computed."""
    sandbox.check(FORGING_SPEC, {}, FORGING_HISTORY, ["door.open()"], "tenant-a")
    out = []
    for warm in (True, False):
        (verdict,) = sandbox.check(DOOR_SPEC, LOCKED, LOCKED_HISTORY, ["door.open()"], "tenant-a", warm=warm)
        out.append(verdict.allowed)
    return out


def hanging_child(sandbox: Sandbox) -> list[str | None]:
    """Two calls of one tenant whose warm child, from the second call on, writes a byte and hangs: the error of
    each (None: answered, allowed)."""
    out: list[str | None] = []
    for _ in range(2):
        try:
            (verdict,) = sandbox.check(HANGS_AFTER_A_BYTE, {}, HISTORY, ["room.enter()"], "tenant-a")
        except LimitExceeded as exc:
            out.append(str(exc))
            continue
        out.append(None if verdict.allowed and verdict.error is None else str(verdict.error))
    return out


def _children_cpu_s(servers: set[int]) -> float:
    """CPU seconds used so far by the children of these fork servers."""
    ticks = 0
    for pid in _pids():
        fields = _stat(pid)
        if fields and int(fields[1]) in servers:
            ticks += int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def _servers() -> set[int]:
    """This process's fork servers (its children)."""
    return {pid for pid in _pids() if (fields := _stat(pid)) and int(fields[1]) == os.getpid()}


def _pids() -> list[int]:
    return [int(entry) for entry in os.listdir("/proc") if entry.isdigit()]


def _stat(pid: int) -> list[str]:
    """/proc/<pid>/stat after the command name: state, ppid, ... (empty when the process is gone)."""
    with contextlib.suppress(OSError), open(f"/proc/{pid}/stat") as stat:
        return stat.read().rpartition(")")[2].split()
    return []


if __name__ == "__main__":
    with Sandbox(LIMITS, workers=1) as box:
        report: dict[str, Any] = {"uid": os.getuid(), "sequence": scope_sequence(box)}
    with Sandbox(LIMITS, workers=1) as box:
        report["idle"] = idle_spin(box)
    with Sandbox(UNIT_LIMITS, workers=1) as box:
        report["unfit"] = unfit_child(box)
    with Sandbox(LIMITS, workers=1) as box:
        report["forged"] = forged_then_unwarmed(box)
        report["hanging"] = hanging_child(box)
    print(json.dumps(report))
    sys.exit(0)
