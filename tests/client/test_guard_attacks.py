"""Attacks on the embedded guard through its rules and its tool results, each run for real in a process of its
own, as root and as a non-root user, under a CPU limit the kernel enforces (a probe that burns CPU is killed, and
fails): a stored rule of nested squarings, a tool result whose values all hash alike under the learner's own set
rule, and rules whose generators Python evaluates otherwise than a lazy reading would. Each must be contained
(refused, or not embeddable) or answered as Python answers it; the squarings are also refused when a set is
stored (`precondition_sets.check_rule_work`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from precond.programs.checks import WORK_BUDGET, ProgramProblem
from precond.store.sets import check_rule_work
from precond_client.rule_interpreter import MAX_INT_BITS, MAX_STEPS
from tests.client.test_guard import SPEC

ROOT = Path(__file__).resolve().parents[2]
R = "self.results['get_reservation_details'][reservation_id]"
PAIRS = (f"{{(x['date'], x['flight_number']) for x in flights}} == "
         f"{{(x['date'], x['flight_number']) for x in {R}['flights']}}")
"""The learner's own rule: the flights asked for are the reservation's."""
GENERATORS = "all(all(all(g) for x in ((),)) for g in [(y['date'] >= '2024-05-15' for y in x) for x in (flights,)])"
"""`all(y['date'] >= '2024-05-15' for y in flights)` to Python: `g` iterates `flights`, read when `g` was made."""
LAST_VALUE = "all(all(g) for g in [(f['date'] >= '2024-05-15' for y in (1,)) for f in flights])"
"""Each generator reads `f` when consumed, after its comprehension ended: the last flight, as a closure does."""


def squarings(levels: int, base: str = "(0xff,)") -> str:
    """The 533-character rule of 26 nested squarings of a constant, or fewer levels over `base`."""
    inner = f"[v0*v0 for v0 in {base}]"
    for level in range(1, levels):
        inner = f"[v{level}*v{level} for v{level} in {inner}]"
    return f"len({inner}) == 1"


POWERS = ("len([v*v*v*v*v*v*v*v for v in [w*w*w*w*w*w*w*w for w in [u*u*u*u*u*u*u*u for u in (amount,)]]]) "
          "== 1")
"""Within the nesting bound, over the call's argument: a 3,900-digit amount to the 512th power."""

PROBE = """
import json, resource, sys, time
resource.setrlimit(resource.RLIMIT_CPU, (10, 10))
from precond_client.guard import Guard, NotEmbeddable
spec, squarings, powers, pairs, generators, last_value = sys.argv[1:7]
P = 2**61 - 1
out = {}
try:
    Guard(spec, {"AGENT.cancel_reservation": [squarings]})
    out["squarings"] = "embedded"
except NotEmbeddable as exc:
    out["squarings"] = "not embeddable: " + str(exc)[-80:]

def verdict(rules, history, name, arguments):
    start = time.process_time()
    found = Guard(spec, rules).session(history).check(name, json.dumps(arguments))
    return {"allowed": found.allowed, "error": (found.error or "")[-160:], "cpu_s": time.process_time() - start}

certificate = {"user_id": "u1", "amount": int("7" * 3900)}
out["powers"] = verdict({"AGENT.send_certificate": [powers]}, [], "send_certificate", certificate)

def read(flights):
    result = {"reservation_id": "BIG001", "flights": flights}
    return [{"role": "user", "content": "change BIG001"},
            {"role": "assistant", "tool_calls": [{"id": "c1", "type": "function", "function": {
                "name": "get_reservation_details", "arguments": '{"reservation_id": "BIG001"}'}}]},
            {"role": "tool", "tool_call_id": "c1", "content": json.dumps(result)}]

alike = read([{"flight_number": 7 + i * P, "date": "2024-05-20"} for i in range(30000)])
change = {"reservation_id": "BIG001", "cabin": "economy", "payment_id": "gift_card_1",  # arguments its tool's
          "flights": [{"flight_number": "HAT007", "date": "2024-05-20"}]}  # schema allows: the result attacks
out["alike"] = verdict({"AGENT.update_reservation_flights": [pairs]}, alike, "update_reservation_flights", change)
flown = {**change, "flights": [{"flight_number": "HAT1", "date": "2024-05-01"}, {"flight_number": "HAT2",
                                                                                  "date": "2024-05-20"}]}
out["generators"] = verdict({"AGENT.update_reservation_flights": [generators]}, [], "update_reservation_flights",
                            flown)
out["last_value"] = verdict({"AGENT.update_reservation_flights": [last_value]}, [], "update_reservation_flights",
                            flown)
print(json.dumps(out))
"""


@pytest.mark.parametrize("user", ["root", "nobody"])
def test_rules_and_results_that_burn_cpu_or_read_generators_late_are_contained_as_root_or_not(
        user: str, tmp_path: Path) -> None:
    if user == "nobody" and os.geteuid() != 0:
        pytest.skip("already not root: the root case ran as this user")
    tmp_path.chmod(0o777)
    prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if user == "nobody" else []
    done = subprocess.run([*prefix, sys.executable, "-c", PROBE, SPEC, squarings(26), POWERS, PAIRS, GENERATORS,
                           LAST_VALUE], cwd=tmp_path, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, f"killed or failed ({done.returncode}): {done.stderr[-2000:]}"
    out = json.loads(done.stdout)
    assert out["squarings"].startswith("not embeddable") and "comprehensions nested" in out["squarings"], out
    assert not out["powers"]["allowed"] and f"more than {MAX_INT_BITS:,} bits" in out["powers"]["error"], out
    assert not out["alike"]["allowed"] and "raised WorkExceeded" in out["alike"]["error"], out
    # Python: the first flight was flown (2024-05-01), so `all(...)` is false: refused, no error
    assert out["generators"] == {**out["generators"], "allowed": False, "error": ""}, out
    # Python: every generator reads the last flight (2024-05-20): allowed
    assert out["last_value"] == {**out["last_value"], "allowed": True, "error": ""}, out


def test_a_rule_whose_constant_part_runs_past_the_budget_is_refused_when_stored_naming_it_and_the_bound() -> None:
    with pytest.raises(ProgramProblem) as raised:
        check_rule_work({"AGENT.cancel_reservation": ["reservation_id != ''", squarings(26)]})
    problem = raised.value.problem
    assert problem.type == WORK_BUDGET and problem.field == "preconditions.AGENT.cancel_reservation[1]"
    assert "len([v25*v25 for v25 in" in problem.message and f"{MAX_INT_BITS:,} bits" in problem.message
    with pytest.raises(ProgramProblem, match=f"budget of steps \\({MAX_STEPS:,} a call\\)"):
        check_rule_work({"AGENT.cancel_reservation": ["len((0,) * 100000 * 100000) > 0 and reservation_id != ''"]})


def test_rules_whose_constant_parts_are_cheap_or_read_the_state_are_stored() -> None:
    check_rule_work({"AGENT.cancel_reservation": [squarings(3), squarings(26, "(reservation_id,)"), PAIRS,
                                                  GENERATORS, "max(0, total - 2 * len([1, 2])) == 0",
                                                  "len(x) > 1 / 0", "not a rule ("]})
