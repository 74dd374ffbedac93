"""The embedded guard's worst checks: the CPU time of one `Session.check` under hostile rules and a hostile tool
result of about 1 MB, each the most a check can be made to cost through that path before its bounds refuse it.

    python bench/guard_worst_case_bench.py [--repeat 3] [--json out.json]

Each case is a set of rules for `update_reservation_flights` (or `send_certificate`) and a history whose one
`get_reservation_details` result is about 1 MB of JSON, or a call whose argument is as large as a call may be:

- `alike`: the learner's own rule, the flights asked for compared as a set of (date, number) pairs with the read
  reservation's, whose numbers all hash alike (`n + k * (2**61 - 1)`); `distinct`: the same with plain numbers.
- `linear`, `quadratic`, `cubic`: a comprehension over the flights, and comparisons of every pair (triple).
- `nested_equal`: a 1 MB nested value compared with a copy of itself; `member`: a nested value looked up in it.
- `search`: a long argument searched for in a 1 MB string that holds all of it but its last character.
- `powers`: a 3,900-digit argument to the 512th power (three nested comprehensions of eighth powers).
- `squarings`: the 26 nested squarings of a constant: not embeddable (the load is what is timed), and refused
  when a set is stored.

For each, the verdict (allowed, refused, or the error's type) and the check's CPU time (the process's, the most
of `--repeat`). The bound the guard keeps: `rule_interpreter.MAX_STEPS` steps a call.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.guard_bench import cpu  # noqa: E402
from precond.convert.openai import convert  # noqa: E402
from precond_client.guard import Guard, NotEmbeddable  # noqa: E402
from precond_client.rule_interpreter import MAX_STEPS  # noqa: E402

TAU = ROOT / "tests" / "fixtures" / "tau_airline"
R = "self.results['get_reservation_details'][reservation_id]"
P = 2**61 - 1
RULES = {
    "alike": f"{{(x['date'], x['flight_number']) for x in flights}} == "
             f"{{(x['date'], x['flight_number']) for x in {R}['flights']}}",
    "linear": f"all(x['date'] >= '2024-05-15' for x in {R}['flights'])",
    "quadratic": f"all(all(x['date'] == y['date'] for y in {R}['flights']) for x in {R}['flights'])",
    "cubic": f"all(all(all(x['date'] == y['date'] for x in {R}['flights']) for y in {R}['flights']) "
             f"for z in {R}['flights'])",
    "nested_equal": f"{R}['nested'] == {R}['copy']",
    "member": f"{R}['copy'] in {R}['nested']",
    "search": f"payment_id in {R}['note']",
}
RULES["distinct"] = RULES["alike"]
POWERS = "len([v*v*v*v*v*v*v*v for v in [w*w*w*w*w*w*w*w for w in [u*u*u*u*u*u*u*u for u in (amount,)]]]) == 1"


def squarings(levels: int = 26) -> str:
    inner = "[v0*v0 for v0 in (0xff,)]"
    for level in range(1, levels):
        inner = f"[v{level}*v{level} for v{level} in {inner}]"
    return f"len({inner}) == 1"


def result(case: str) -> dict[str, Any]:
    """About 1 MB of JSON for the case."""
    if case in ("alike", "distinct", "linear", "quadratic", "cubic"):
        flights = [{"flight_number": 7 + (i * P if case == "alike" else i), "date": "2024-05-20"}
                   for i in range(20_000)]
        return {"reservation_id": "BIG001", "flights": flights}
    if case in ("nested_equal", "member"):
        nested = [[{"a": [i, str(i)], "b": {"c": i}} for i in range(50)] for _ in range(400)]
        return {"reservation_id": "BIG001", "nested": nested, "copy": json.loads(json.dumps(nested))}
    return {"reservation_id": "BIG001", "note": "a" * 1_000_000}


def history(case: str) -> tuple[list[dict[str, Any]], int]:
    content = json.dumps(result(case))
    return [{"role": "user", "content": "change BIG001"},
            {"role": "assistant", "tool_calls": [{"id": "c1", "type": "function", "function": {
                "name": "get_reservation_details", "arguments": '{"reservation_id": "BIG001"}'}}]},
            {"role": "tool", "tool_call_id": "c1", "content": content}], len(content)


def timed(check: Callable[[], Any], repeat: int) -> tuple[Any, float]:
    worst, answer = 0.0, None
    for _ in range(repeat):
        start = time.process_time()
        answer = check()
        worst = max(worst, time.process_time() - start)
    return answer, worst


def outcome(verdict: Any) -> str:
    if verdict.allowed:
        return "allowed"
    if verdict.error:
        return "refused: " + str(verdict.error).rpartition(" raised ")[2].split(":")[0]
    return "refused"


def run(spec: str, repeat: int) -> dict[str, Any]:
    found: dict[str, Any] = {}
    change = {"reservation_id": "BIG001", "cabin": "economy", "payment_id": "a" * 2999 + "b",
              "flights": [{"flight_number": "HAT007", "date": "2024-05-20"}]}  # keeps the schema: the rules run
    for case, rule in RULES.items():
        messages, size = history(case)
        session = Guard(spec, {"AGENT.update_reservation_flights": [rule]}).session(messages)
        verdict, cpu = timed(partial(session.check, "update_reservation_flights", json.dumps(change)), repeat)
        found[case] = {"result_bytes": size, "verdict": outcome(verdict), "check_cpu_ms": round(cpu * 1e3, 2)}
    certificate = json.dumps({"user_id": "u1", "amount": int("7" * 3900)})
    session = Guard(spec, {"AGENT.send_certificate": [POWERS]}).session()
    verdict, cpu = timed(partial(session.check, "send_certificate", certificate), repeat)
    found["powers"] = {"argument_digits": 3900, "verdict": outcome(verdict), "check_cpu_ms": round(cpu * 1e3, 2)}

    def load() -> str:
        try:
            Guard(spec, {"AGENT.cancel_reservation": [squarings()]})
        except NotEmbeddable:
            return "not embeddable"
        return "embedded"

    embedded, cpu = timed(load, repeat)
    found["squarings"] = {"rule_chars": len(squarings()), "verdict": embedded, "load_cpu_ms": round(cpu * 1e3, 2)}
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3, help="checks per case (the most is reported)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    records = json.loads((TAU / "trajectories.json").read_text())
    spec = convert(records, json.loads((TAU / "tools.json").read_text())).spec
    cases = run(spec, args.repeat)
    results = {"cpu": cpu(), "python": platform.python_version(), "budget_steps": MAX_STEPS, "cases": cases,
               "worst_check_cpu_ms": max(c.get("check_cpu_ms", 0.0) for c in cases.values())}
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
