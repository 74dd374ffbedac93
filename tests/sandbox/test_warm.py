"""Warm children (`sandbox.child.server`): a check that names a scope may be answered by a child that answered
that scope before and kept what it compiled. The attacks: a tenant leaves state in its warm child, and another
tenant's check (or one with no scope) must never run there; a warm child made unfit by its past calls must not
change what the next call may use or answers."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator

import pytest
from sandbox_helpers import COUNTING_SPEC, SMALL

from sandbox import Limits, Sandbox

HISTORY = "room = Room()\nroom.mark()\n"
FIRST_TIME = {"Room.enter": ["self.marks == 1"]}


@pytest.fixture()
def one_server() -> Iterator[Sandbox]:
    """One fork server, so that every call goes to the same one (and its warm children)."""
    with Sandbox(SMALL, workers=1) as sandbox:
        yield sandbox


def allowed(sandbox: Sandbox, scope: str | None) -> bool:
    (verdict,) = sandbox.check(COUNTING_SPEC, FIRST_TIME, HISTORY, ["room.enter()"], scope)
    assert verdict.error is None, verdict.error
    return verdict.allowed


def test_a_warm_child_is_reused_by_its_own_scope_only(one_server: Sandbox) -> None:
    assert allowed(one_server, "tenant-a")
    assert not allowed(one_server, "tenant-a")  # the same child: it kept its process, and the count
    assert allowed(one_server, "tenant-b")  # never tenant-a's child
    assert allowed(one_server, None)  # no scope: always a fresh child, never kept
    assert allowed(one_server, None)
    assert not allowed(one_server, "tenant-b")
    assert not allowed(one_server, "tenant-a")


SLOW_AFTER_FIRST = """
import collections

class Room:
    def mark(self):
        collections.marks = getattr(collections, 'marks', 0) + 1
    def enter(self):
        while collections.marks > 1:
            pass
"""


def test_a_failure_on_a_warm_child_is_run_again_on_a_fresh_one() -> None:
    """From its second call on, the warm child loops in the proposed call (its past left it that way): the
    call's part runs out of CPU there, and the same call on a fresh child answers as a first call does."""
    with Sandbox(Limits(timeout_s=20, cpu_s=20, unit_cpu_s=0.5), workers=1) as sandbox:
        for _ in range(3):
            (verdict,) = sandbox.check(SLOW_AFTER_FIRST, {}, HISTORY, ["room.enter()"], "tenant-a")
            assert verdict.allowed and verdict.error is None


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


def _children_cpu_s(servers: set[int]) -> float:
    """CPU seconds used so far by the children of these fork servers."""
    ticks = 0
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                fields = stat.read().rpartition(")")[2].split()
        except OSError:
            continue
        if int(fields[1]) in servers:
            ticks += int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def _servers() -> set[int]:
    """This test process's fork servers (its children running the sandbox's bootstrap)."""
    found = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError), open(f"/proc/{entry}/stat") as stat:
                if int(stat.read().rpartition(")")[2].split()[1]) == os.getpid():
                    found.add(int(entry))
    return found


def test_a_warm_child_uses_no_cpu_while_it_waits_and_a_stuck_one_is_replaced(one_server: Sandbox) -> None:
    def check() -> bool:
        (verdict,) = one_server.check(SPINS_WHEN_IDLE, {}, HISTORY, ["room.enter()"], "tenant-a")
        return verdict.allowed and verdict.error is None

    assert check()
    servers = _servers()
    before = _children_cpu_s(servers)
    time.sleep(1.0)
    assert _children_cpu_s(servers) - before < 0.3  # stopped while it waits: on the old warm child, ~1.0
    started = time.monotonic()
    assert check()  # the stuck child does not answer; a fresh one does, well before the call's deadline
    assert time.monotonic() - started < SMALL.timeout_s / 2
