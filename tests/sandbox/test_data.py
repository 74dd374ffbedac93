"""Correctness on SGD and ALFWorld data (tests/fixtures), against ground truth and an independent replay."""

from __future__ import annotations

import ast
import copy
from collections import defaultdict
from typing import Any

import pytest
from sandbox_helpers import DATA, alfworld, sgd

from precond.sandbox import Point, Sandbox

DOMAINS = ["Restaurants_1", "Events_1"]


def gt(domain: dict[str, Any]) -> dict[str, list[str]]:
    return {f"SYSTEM.{a}": list(e) for a, e in domain["gt_preconditions"].items()}


@pytest.mark.parametrize("name", DOMAINS)
def test_sgd_ground_truth_is_valid(big: Sandbox, name: str) -> None:
    domain = sgd(name)
    result = big.evaluate(domain["spec_program"], [d["program"] for d in domain["demos"]], gt(domain))
    for action, candidates in result.results.items():
        for candidate in candidates:
            assert candidate.status == "valid", (action, candidate)
            assert candidate.satisfied, (action, candidate)


def test_sgd_wrong_assertions_are_invalid(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    wrong = ["False", "self.user.no_more and not self.user.no_more", "self.user.selected",
             "self.user.informed_slot[slot]", "1 / 0 == 0"]
    result = big.evaluate(domain["spec_program"], [d["program"] for d in domain["demos"]],
                          {"SYSTEM.REQUEST": wrong, "SYSTEM.GOODBYE": ["not self.user.no_more"]})
    for candidate in result.results["SYSTEM.REQUEST"] + result.results["SYSTEM.GOODBYE"]:
        assert candidate.status == "invalid", candidate
        assert candidate.reason and "demonstration" in candidate.reason and "line" in candidate.reason
    assert result.results["SYSTEM.REQUEST"][0].satisfied == 0
    assert "ZeroDivisionError" in (result.results["SYSTEM.REQUEST"][4].reason or "")


def replay(spec: str, program: str) -> list[dict[str, Any]]:
    """Trusted, in-process replay: the variables before each top-level statement (deep copies)."""
    namespace: dict[str, Any] = {}
    exec(spec, namespace)
    base = dict(namespace)
    snapshots = []
    for statement in ast.parse(program).body:
        variables = {k: v for k, v in namespace.items() if k not in base}
        snapshots.append(copy.deepcopy(variables))
        exec(compile(ast.Module([statement], []), "<demo>", "exec"), namespace)
    return snapshots


def independent_bits(spec: str, demos: list[str], action: str, params: str, expression: str,
                     points: tuple[Point, ...]) -> int:
    namespace: dict[str, Any] = {"defaultdict": defaultdict}
    exec(spec, namespace)
    check = eval(f"lambda self, {params}: ({expression})" if params else f"lambda self: ({expression})",
                 namespace)
    snapshots = [replay(spec, d) for d in demos]
    cls = action.split(".")[0]
    bits = 0
    for k, point in enumerate(points):
        state = snapshots[point.demo][point.position]
        selves = [v for v in state.values() if type(v).__name__ == cls]
        if not selves:
            continue
        try:
            if check(copy.deepcopy(selves[0]), *point.args):
                bits |= 1 << k
        except Exception:
            pass
    return bits


CASES = [
    ("SYSTEM.INFORM", "slot", "self.user.requested_slot[slot]"),
    ("SYSTEM.REQUEST", "slot", "not self.user.informed_slot[slot]"),
    ("SYSTEM.REQUEST", "slot", "slot in self.user.informed_slot"),
    ("SYSTEM.CONFIRM", "slot", "self.user.selected or self.user.informed_slot['restaurant_name']"),
    ("SYSTEM.OFFER", "slot", "self.query_success or self.user.affirmed"),
    ("SYSTEM.REQ_MORE", "", "self.user.selected or self.user.no_more or not self.query_success"),
    ("SYSTEM.NOTIFY_FAILURE", "", "not self.query_success"),
    ("SYSTEM.GOODBYE", "", "self.user.informed_slot['city'] and len(self.user.requested_slot) > 0"),
]


def test_sgd_satisfaction_matches_independent_replay(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    spec, demos = domain["spec_program"], [d["program"] for d in domain["demos"]]
    candidates: dict[str, list[str]] = {}
    for action, _, expression in CASES:
        candidates.setdefault(action, []).append(expression)
    result = big.evaluate(spec, demos, candidates)
    seen: dict[str, int] = {}
    for action, params, expression in CASES:
        index = seen[action] = seen.get(action, -1) + 1
        points = result.points[action]
        assert points, action
        expected = independent_bits(spec, demos, action, params, expression, points)
        assert result.results[action][index].satisfied == expected, (action, expression)


def test_sgd_default_points(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    spec, demos = domain["spec_program"], [d["program"] for d in domain["demos"]]
    traced = big.trace(spec, demos)
    values = traced.actions["SYSTEM.REQUEST"].arg_values
    result = big.evaluate(spec, demos, {"SYSTEM.REQUEST": ["True"], "SYSTEM.GOODBYE": ["True"]})
    points = result.points["SYSTEM.REQUEST"]
    # `system` exists from position 2 on (after `user = USER()` and `system = SYSTEM(user)`)
    expected = [Point(d, p, v) for d, pos in enumerate(traced.positions) for p in range(2, len(pos))
                for v in values]
    assert list(points) == expected
    assert result.results["SYSTEM.REQUEST"][0].satisfied == (1 << len(points)) - 1
    assert {p.args for p in result.points["SYSTEM.GOODBYE"]} == {()}


def test_sgd_trace(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    demos = [d["program"] for d in domain["demos"]]
    traced = big.trace(domain["spec_program"], demos)
    assert [len(p) for p in traced.positions] == [len(d.strip().splitlines()) for d in demos]
    assert traced.positions[0][3].source == "system.REQUEST('city')"
    assert traced.positions[0][3].line == 4
    request = traced.actions["SYSTEM.REQUEST"]
    assert request.stub and request.params == ("slot",)
    assert request.occurrences[0] == Point(0, 3, ("city",))
    assert not traced.actions["SYSTEM.set_query_status"].stub
    assert traced.actions["USER.INFORM"].occurrences
    assert set(traced.actions) == {f"SYSTEM.{a}" for a in domain["system_actions"]} | {
        f"USER.{a}" for a in domain["user_actions"]} | {"SYSTEM.set_query_status"}


def gt_assertions(source: str) -> dict[str, list[str]]:
    """`Class.method` -> the assert expressions of its body, read with ast."""
    result: dict[str, list[str]] = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    asserts = [ast.unparse(s.test) for s in item.body if isinstance(s, ast.Assert)]
                    if asserts:
                        result[f"{node.name}.{item.name}"] = asserts
    return result


def test_alfworld_ground_truth_on_demonstrations(big: Sandbox) -> None:
    spec = (DATA / "alfworld" / "alfworld_spec.py").read_text()
    assertions = gt_assertions((DATA / "alfworld" / "alfworld_spec_gt.py").read_text())
    assert len(assertions) == 9
    demos = [t["program"] for t in alfworld("demos.json")["trajectories"]]
    result = big.evaluate(spec, demos, assertions)
    for action, candidates in result.results.items():
        for candidate in candidates:
            expected = "valid"
            assert candidate.status == expected, (action, candidate)
    assert result.results["Agent.goto"][0].satisfied
    wrong = big.evaluate(spec, demos, {"Agent.take": ["self.inventory == obj", "'sink' in recep"]})
    assert [c.status for c in wrong.results["Agent.take"]] == ["invalid", "invalid"]


def test_alfworld_ground_truth_on_test_trajectories(big: Sandbox) -> None:
    spec = (DATA / "alfworld" / "alfworld_spec.py").read_text()
    assertions = gt_assertions((DATA / "alfworld" / "alfworld_spec_gt.py").read_text())
    programs = [t["program"] for t in alfworld("test.json")["trajectories"]]
    assert len(programs) == 12
    chunk = 5
    for start in range(0, len(programs), chunk):
        demos = programs[start:start + chunk]
        traced = big.trace(spec, demos)
        points = {a: traced.actions[a].occurrences for a in assertions}
        result = big.evaluate(spec, demos, assertions, points)
        for action, candidates in result.results.items():
            everywhere = (1 << len(points[action])) - 1
            for candidate in candidates:
                assert candidate.status == "valid", (start, action, candidate)
                assert candidate.satisfied == everywhere, (start, action, candidate.expression)


def test_check_sgd_history(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    lines = domain["demos"][0]["program"].strip().splitlines()
    history = "\n".join(lines[:5])  # ... user.INFORM('city')
    calls = ["system.REQUEST('cuisine')", "system.REQUEST('city')", "system.FindRestaurants()",
             "system.GOODBYE()", "system.NOPE()", "system.REQUEST()", "user.SELECT()", "nobody.REQUEST('x')"]
    verdicts = big.check(domain["spec_program"], gt(domain), history, calls)
    by_call = {v.call: v for v in verdicts}
    assert by_call["system.REQUEST('cuisine')"].allowed
    assert by_call["system.REQUEST('city')"].violations == ("not self.user.informed_slot[slot]",)
    assert by_call["system.FindRestaurants()"].violations == ("self.user.informed_slot['cuisine']",)
    assert by_call["system.GOODBYE()"].violations == ("self.user.no_more",)
    for call in ("system.NOPE()", "system.REQUEST()", "nobody.REQUEST('x')"):
        assert not by_call[call].allowed and by_call[call].error, call
    assert by_call["user.SELECT()"].allowed


def test_check_reports_every_violation_and_calls_are_independent(big: Sandbox) -> None:
    domain = sgd("Restaurants_1")
    history = "user = USER()\nsystem = SYSTEM(user)"
    verdicts = big.check(domain["spec_program"], gt(domain), history,
                         ["system.FindRestaurants()", "user.INFORM('city')", "system.CONFIRM('time')"])
    assert verdicts[0].violations == tuple(gt(domain)["SYSTEM.FindRestaurants"])
    assert verdicts[1].allowed
    # the INFORM above ran on its own copy: 'city' is still not informed for the CONFIRM
    assert "self.user.informed_slot['city']" in verdicts[2].violations


def test_check_alfworld_function_history(big: Sandbox) -> None:
    spec = (DATA / "alfworld" / "alfworld_spec.py").read_text()
    assertions = gt_assertions((DATA / "alfworld" / "alfworld_spec_gt.py").read_text())
    program = alfworld("demos.json")["trajectories"][0]["program"]
    verdicts = big.check(spec, assertions, program,
                         ["agent.goto('toilet 1')", "agent.take('cloth 1', 'cabinet 1')",
                          "agent.heat('spraybottle 2', 'toilet 1')"])
    assert verdicts[0].allowed
    assert verdicts[1].violations == () and verdicts[1].allowed
    assert set(verdicts[2].violations) == {"self.inventory == obj", "'microwave' in recep"}


def test_history_error_is_program_error(big: Sandbox) -> None:
    from precond.sandbox import ProgramError

    domain = sgd("Restaurants_1")
    with pytest.raises(ProgramError) as caught:
        history = "user = USER()\nsystem = SYSTEM(user)\nsystem.DANCE()"
        big.check(domain["spec_program"], gt(domain), history, ["user.SELECT()"])
    assert caught.value.where == "history" and caught.value.line == 3
    assert caught.value.exc_type == "AttributeError"


DICT_SPEC = """
class AGENT:
  def __init__(self):
    self.paid = 0
  def book(self, user, payment_methods):
    self.paid += 1
"""
DICT_DEMO = """
agent = AGENT()
agent.book('mia', [{'payment_id': 'certificate_1', 'amount': 250}, {'payment_id': 'credit_card_2', 'amount': 5}])
agent.book('mia', [{'payment_id': 'certificate_1', 'amount': 50}, {'payment_id': 'certificate_3', 'amount': 5}])
"""


def test_object_arguments_are_judged_as_the_dicts_they_are(big: Sandbox) -> None:
    """A list of objects passed to an action (payment methods) reaches the conditions as dicts, at the
    demonstrated calls and at points given back: counting them by a field is a condition that can hold."""
    one = "len([x for x in payment_methods if 'certificate_' in x['payment_id']]) <= 1"
    result = big.evaluate(DICT_SPEC, [DICT_DEMO], {"AGENT.book": [one, "payment_methods[0]['amount'] >= 50"]})
    points = result.points["AGENT.book"]
    first = next(p for p in points if p.position == 1 and p.args[1][1]["payment_id"] == "credit_card_2")
    counted, amount = result.results["AGENT.book"]
    assert counted.status == "invalid" and counted.satisfied >> points.index(first) & 1
    assert amount.status == "valid"
    second = next(p for p in points if p.position == 2 and p.args[1][1]["payment_id"] == "certificate_3")
    assert not counted.satisfied >> points.index(second) & 1
    again = big.evaluate(DICT_SPEC, [DICT_DEMO], {"AGENT.book": [one]}, {"AGENT.book": [first, second]})
    assert again.results["AGENT.book"][0].satisfied == 0b01
    assert {first, second} == set(again.points["AGENT.book"]) and hash(first) == hash(Point(0, 1, first.args))
