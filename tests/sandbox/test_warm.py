"""Warm children (`sandbox.child.server`): a check that names a scope (its tenant) may be answered by a child
that answered that scope before and kept what it compiled. The attacks (`warm_probe.py`), as root here and as
a non-root user in `test_boundary.py`: a tenant leaves state in its warm child, and another tenant's check (or
one with no scope) must never run there; a warm child left spinning must not use a CPU while it waits; a warm
child made unfit by its past calls (or one that answers a byte and hangs) must not change what the next call may
use or answers; a call without warm children (a result shared between tenants) never runs where its tenant's
history forged the verdicts."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from warm_probe import (
    COUNTING_SPEC,
    EXPECTED,
    FIRST_TIME,
    HISTORY,
    LIMITS,
    UNIT_LIMITS,
    forged_then_unwarmed,
    hanging_child,
    idle_spin,
    scope_sequence,
    unfit_child,
)

from precond.sandbox import Sandbox


@pytest.fixture()
def one_server() -> Iterator[Sandbox]:
    """One fork server, so that every call goes to the same one (and its warm children)."""
    with Sandbox(LIMITS, workers=1) as sandbox:
        yield sandbox


def test_a_warm_child_is_reused_by_its_own_scope_only(one_server: Sandbox) -> None:
    # a, a (the same child: it kept the count), b (never a's child), no scope twice (always fresh, never kept),
    # b (b's own warm child), a (a's, still there)
    assert scope_sequence(one_server) == EXPECTED


def test_a_scope_goes_back_to_the_server_of_its_warm_child() -> None:
    """With several servers, a tenant's calls go to the one holding its warm child (taken in turn, each of
    the three servers answered a's first three calls with a fresh child), and a new tenant to another one."""
    def first_time(scope: str) -> bool:
        (verdict,) = sandbox.check(COUNTING_SPEC, FIRST_TIME, HISTORY, ["room.enter()"], scope)
        return verdict.allowed and verdict.error is None

    with Sandbox(LIMITS, workers=3) as sandbox:
        assert [first_time(scope) for scope in ("a", "a", "b", "a", "b", "a")] == [True, False, True, False, False,
                                                                                  False]


def test_a_warm_child_uses_no_cpu_while_it_waits_and_a_stuck_one_is_replaced(one_server: Sandbox) -> None:
    seen = idle_spin(one_server)
    assert seen["first"] and seen["second"]
    assert seen["idle_cpu_s"] < 0.3  # stopped while it waits: on a warm child that is not, ~1.0
    assert seen["second_s"] < LIMITS.timeout_s / 2  # the stuck child is passed over well before the deadline


def test_a_failure_on_a_warm_child_is_run_again_on_a_fresh_one() -> None:
    """From its second call on, the warm child loops in the proposed call: that part runs out of CPU there,
    and the same call on a fresh child answers as a first call does."""
    with Sandbox(UNIT_LIMITS, workers=1) as sandbox:
        assert unfit_child(sandbox) == [True, True, True]


def test_a_call_without_warm_children_never_runs_where_its_tenant_forged_the_verdicts(one_server: Sandbox) -> None:
    """A history replaced the verdict function of its tenant's warm child: there, a locked door opens (the
    tenant's own state); with `warm=False`, as the worker computes a result it shares between tenants, the call
    runs on a fresh child and the rule refuses it."""
    assert forged_then_unwarmed(one_server) == [True, False]


def test_a_fresh_child_after_a_warm_one_gets_a_whole_deadline(one_server: Sandbox) -> None:
    """The warm child writes a byte (so it is not stalled) and hangs until the call's deadline; the call then
    runs on a fresh child with a deadline of its own, and answers as a first call does."""
    assert hanging_child(one_server) == [None, None]


def test_a_remembered_history_line_is_the_line_python_read(one_server: Sandbox) -> None:
    """Lines are remembered by their place and text; a character that `str.splitlines` breaks at and Python's
    parser does not (`\\x1c` in a string) must not shift which text a statement is remembered under: the
    second history's `box.put(3)` would then have run as the first one's `box.put(2)`."""
    spec = "class Box:\n    def put(self, v):\n        self.v = v\n    def take(self):\n        pass\n"
    rule = {"Box.take": ["self.v == 3"]}
    for value, expected in ((2, False), (3, True)):
        history = f"box = Box()\nbox.put('\\x1c')\nbox.put({value})\n".replace("\\x1c", "\x1c")
        (verdict,) = one_server.check(spec, rule, history, ["box.take()"], "tenant-a")
        assert verdict.error is None and verdict.allowed is expected
