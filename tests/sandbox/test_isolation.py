"""Candidates cannot change what other candidates see, whatever order they come in."""

from __future__ import annotations

import pytest
from sandbox_helpers import sgd

from precond.sandbox import Sandbox

MUTABLE_SPEC = """
class Box:
    def __init__(self):
        self.items = []
        self.count = 0
    def put(self, x):
        self.items.append(x)
    def bump(self):
        self.count += 1
        return True
    def size(self):
        return len(self.items)
    def act(self, x):
        pass
"""
MUTABLE_DEMO = "b = Box()\nb.act(1)\nb.put(1)\nb.act(2)\nb.put(2)\nb.act(3)\n"


def test_defaultdict_reads_do_not_leak(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    spec, demos = domain["spec_program"], [d["program"] for d in domain["demos"]]
    alone = big.evaluate(spec, demos, {"SYSTEM.REQUEST": ["slot in self.user.informed_slot"]})
    after = big.evaluate(spec, demos, {"SYSTEM.REQUEST": [
        "self.user.informed_slot[slot]", "slot in self.user.informed_slot",
        "self.user.informed_slot[slot] or slot in self.user.informed_slot",
        "slot in self.user.informed_slot",
    ]})
    (first,) = alone.results["SYSTEM.REQUEST"]
    results = after.results["SYSTEM.REQUEST"]
    assert results[1].satisfied == first.satisfied == results[3].satisfied
    assert first.status == "invalid"  # the dialogs request slots before anything about them is known


def test_mutating_candidates_do_not_change_others(big: Sandbox) -> None:
    probe = "self.size() == 0 and self.count == 0"
    alone = big.evaluate(MUTABLE_SPEC, [MUTABLE_DEMO], {"Box.act": [probe]})
    mixed = big.evaluate(MUTABLE_SPEC, [MUTABLE_DEMO], {"Box.act": [
        "self.bump()", "self.put(x) is None", probe, "self.items.append(9) is None", "self.bump()", probe,
    ]})
    results = mixed.results["Box.act"]
    (expected,) = alone.results["Box.act"]
    assert results[2].satisfied == results[5].satisfied == expected.satisfied
    assert results[0].status == "valid" and results[4].status == "valid"  # count never grows across them
    assert results[1].status == "valid"


@pytest.mark.parametrize("expression", ["self.size() == 0", "len(self.items) == 0"])
def test_occurrences_see_the_state_at_call_time(big: Sandbox, expression: str) -> None:
    demo = "b = Box()\nfor i in range(3):\n    b.act(i)\n    b.put(i)\n"
    result = big.evaluate(MUTABLE_SPEC, [demo], {"Box.act": [expression, "len(self.items) == x"]})
    first, exact = result.results["Box.act"]
    assert first.status == "invalid" and "line 3" in (first.reason or "")
    assert exact.status == "valid"
