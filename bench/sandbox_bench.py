"""Throughput and latency of the sandbox on the SGD development data (a benchmark, not a test).

Reads sgd/ of PRECOND_DATA_DIR (default ../shared/data).

    python bench/sandbox_bench.py [--domain Restaurants_1] [--candidates 500] [--json PATH]

Reports candidate×point evaluations per second for `evaluate`, p50/p95 latency of a trivial `check`,
cold start (Sandbox() to first result), the cost of one call (a fresh confined child: p50 of a trivial
`trace`), and the extra cost of one candidate that is not plain and so is judged in a child of its own.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from precond.evaluation.settings import data_path
from precond.sandbox import Limits, Sandbox

ATOMS = (
    "self.user.requested_slot[slot]", "not self.user.requested_slot[slot]",
    "self.user.informed_slot[slot]", "not self.user.informed_slot[slot]", "self.query_success",
    "not self.query_success", "self.user.selected", "self.user.affirmed", "self.user.no_more",
    "self.user.selected or self.user.no_more", "slot in self.user.informed_slot",
)


def candidates(domain: dict[str, Any], count: int) -> dict[str, list[str]]:
    """GT assertions first, then generated atoms, spread round-robin over the SYSTEM actions."""
    actions = [f"SYSTEM.{a}" for a in domain["gt_preconditions"]]
    pool = [(f"SYSTEM.{a}", e) for a, exprs in domain["gt_preconditions"].items() for e in exprs]
    atoms = list(ATOMS) + [f"self.user.informed_slot[{s!r}]" for s in domain["slots"]]
    atoms += [f"not self.user.informed_intent[{i!r}]" for i in domain["search_intents"]]
    generated = ((a, e) for e, a in itertools.product(atoms, actions))
    chosen: dict[str, list[str]] = {a: [] for a in actions}
    for action, expression in itertools.islice(itertools.chain(pool, itertools.cycle(generated)), count):
        chosen[action].append(expression)
    return chosen


def bench(domain_name: str, count: int, repeats: int) -> dict[str, float]:
    domain = json.loads(data_path("sgd", f"{domain_name}.json").read_text())
    spec, demos = domain["spec_program"], [d["program"] for d in domain["demos"]]
    preconditions = {f"SYSTEM.{a}": e for a, e in domain["gt_preconditions"].items()}
    chosen = candidates(domain, count)
    start = time.perf_counter()
    with Sandbox(Limits(timeout_s=60, cpu_s=60)) as sandbox:
        sandbox.check(spec, {}, "user = USER()", ["user.SELECT()"])
        cold = time.perf_counter() - start
        best = float("inf")
        evaluations = 0
        for _ in range(repeats):
            t0 = time.perf_counter()
            result = sandbox.evaluate(spec, demos, chosen)
            best = min(best, time.perf_counter() - t0)
            evaluations = sum(len(result.points[a]) * len(r) for a, r in result.results.items())
        history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')"
        latencies = timed(200, lambda: sandbox.check(spec, preconditions, history, ["system.REQUEST('city')"]))
        calls = timed(100, lambda: sandbox.trace("class A:\n    pass\n", ["a = A()"]))
        one = {"SYSTEM.REQUEST": ["not self.user.informed_slot[slot]"]}
        plain = timed(20, lambda: sandbox.evaluate(spec, demos, one))
        # Not plain (a name outside the vocabulary): judged in a child of its own.
        alone = timed(20, lambda: sandbox.evaluate(spec, demos, dict(one, **{"SYSTEM.OFFER": ["bool(defaultdict)"]})))
    return {
        "candidates": float(sum(len(v) for v in chosen.values())),
        "evaluations": float(evaluations),
        "evaluate_s": best,
        "evaluations_per_s": evaluations / best,
        "check_p50_ms": 1000 * statistics.median(latencies),
        "check_p95_ms": 1000 * latencies[int(0.95 * len(latencies)) - 1],
        "cold_start_ms": 1000 * cold,
        "call_p50_ms": 1000 * statistics.median(calls),
        "isolated_candidate_ms": 1000 * (statistics.median(alone) - statistics.median(plain)),
    }


def timed(times: int, call: Callable[[], object]) -> list[float]:
    """Sorted wall-clock seconds of `times` calls."""
    latencies = []
    for _ in range(times):
        t0 = time.perf_counter()
        call()
        latencies.append(time.perf_counter() - t0)
    return sorted(latencies)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--domain", default="Restaurants_1")
    parser.add_argument("--candidates", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args()
    figures = bench(args.domain, args.candidates, args.repeats)
    width = max(map(len, figures))
    for name, value in figures.items():
        print(f"{name:<{width}}  {value:>14,.2f}")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
