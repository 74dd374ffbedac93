"""Attacks on the embedded guard's work: a set is the tenant's own text and a history grows with the
conversation, so nested comprehensions could cost the product of what they iterate. Nesting is refused when the
set is loaded; what a call's rules do is counted, and a call whose rules run past the budget is refused with the
reason (fail closed), whichever way the guard fails."""

from __future__ import annotations

import json
from typing import Any

import pytest

from precond_client.guard import Guard, NotEmbeddable
from precond_client.rule_interpreter import MAX_NESTING, MAX_STEPS
from tests.client.test_guard import SPEC

R = "self.results['get_reservation_details'][reservation_id]"
QUADRATIC = f"all(any(x == y for y in {R}['flights']) for x in {R}['flights'])"
LINEAR = f"all(x['date'] >= '2024-05-15' for x in {R}['flights'])"
CANCEL = {"name": "cancel_reservation", "arguments": '{"reservation_id": "BIG001"}'}


def history(flights: int) -> list[dict[str, Any]]:
    """A read of one reservation with `flights` segments: a result as long as the conversation makes it."""
    result = {"reservation_id": "BIG001", "cabin": "economy",
              "flights": [{"flight_number": f"HAT{i:04d}", "date": "2024-05-20"} for i in range(flights)]}
    return [{"role": "user", "content": "cancel BIG001"},
            {"role": "assistant", "tool_calls": [{"id": "c1", "type": "function", "function": {
                "name": "get_reservation_details", "arguments": '{"reservation_id": "BIG001"}'}}]},
            {"role": "tool", "tool_call_id": "c1", "content": json.dumps(result)}]


@pytest.mark.parametrize("fail_closed", [True, False])
def test_nested_comprehensions_over_a_long_result_are_refused_when_they_run_past_the_budget(
        fail_closed: bool) -> None:
    flights = 2000  # 4,000,000 comparisons unbounded: twenty times the budget
    assert flights * flights > 10 * MAX_STEPS
    guard = Guard(SPEC, {"AGENT.cancel_reservation": [QUADRATIC]}, fail_closed=fail_closed)
    verdict = guard.session(history(flights)).check(**CANCEL)
    assert not verdict.allowed
    assert verdict.error is not None and "raised WorkExceeded" in verdict.error and "budget" in verdict.error


def test_the_same_rules_are_judged_within_the_budget() -> None:
    guard = Guard(SPEC, {"AGENT.cancel_reservation": [QUADRATIC, LINEAR]})
    assert guard.session(history(50)).check(**CANCEL).allowed  # 2,500 steps: judged
    assert Guard(SPEC, {"AGENT.cancel_reservation": [LINEAR]}).session(history(20000)).check(**CANCEL).allowed


def test_a_set_nesting_more_comprehensions_is_not_embeddable_naming_the_rule() -> None:
    nested = f"x['date'] for x in {R}['flights']"
    for _ in range(MAX_NESTING):
        nested = f"any(({nested}) for z in {R}['flights'])"
    with pytest.raises(NotEmbeddable) as raised:
        Guard(SPEC, {"AGENT.cancel_reservation": [nested]})
    assert f"more than {MAX_NESTING} comprehensions nested" in str(raised.value) and "rule " in str(raised.value)
