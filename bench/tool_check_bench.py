"""A tool-calling agent's guard through the gateway: `/check-actions` with OpenAI messages and a tool call.

    python bench/tool_check_bench.py [--data ../shared/data/tau-airline] [--n 100] [--json out.json]

Converts the tau-bench airline trajectories (`precond convert openai`'s converter: its time is the first
number), then, on a loopback stack of its own (bench/service_bench.py's: redis-server, gateway, one worker),
sends sequential uncached `/check-actions` requests: for each state-changing call of the runs, the messages
before it as the history and the call as `{"name", "arguments"}`, judged by the read-before-write rules;
then, as the baseline on the same stack, examples/check-actions.json (a short SGD history) with a new call
each time. Every request is new to the cache, so each is a job the worker runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.service_bench import latencies, make_keys, stack  # noqa: E402
from precond.convert.openai import convert  # noqa: E402

READ = "reservation_id in self.results['get_reservation_details']"
WRITES = ("cancel_reservation", "update_reservation_flights", "update_reservation_baggages",
          "update_reservation_passengers")


def bodies(records: list[dict[str, Any]], spec: str, n: int) -> list[dict[str, Any]]:
    """Per state-changing call of the runs: the messages before it, the call (one body each, at most n)."""
    rules = {f"AGENT.{w}": [READ] for w in WRITES}
    out: list[dict[str, Any]] = []
    for record in records:
        for at, message in enumerate(record["traj"]):
            for call in message.get("tool_calls") or []:
                if call["function"]["name"] in WRITES and len(out) < n:
                    out.append({"spec": spec, "preconditions": rules, "history": record["traj"][:at],
                                "calls": [{"name": call["function"]["name"],
                                           "arguments": call["function"]["arguments"]}]})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "tau-airline")
    parser.add_argument("--n", type=int, default=100, help="uncached check-actions requests (after 5 warm-up)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    records = json.loads((args.data / "trajectories.json").read_text())
    tools = json.loads((args.data / "tools.json").read_text())
    started = time.perf_counter()
    converted = convert(records, tools)
    results: dict[str, Any] = {"convert_s": time.perf_counter() - started,
                               "trajectories": len(converted.trajectories)}
    stack_args = argparse.Namespace(model="tiny", root=ROOT, env=[], flood=0, gateway_processes=1)
    with tempfile.TemporaryDirectory(prefix="tool-check-bench-") as name:
        keys = make_keys(Path(name) / "keys.jsonl")
        with stack(stack_args, Path(name)) as base:
            sent = bodies(records, converted.spec, args.n + 5)
            results["check_actions_openai"] = latencies(base, "/check-actions", sent, warmup=5, key=keys["quiet"])
            # the baseline on the same stack: examples/check-actions.json (a short SGD history), a new call each
            example = json.loads((ROOT / "examples" / "check-actions.json").read_text())
            sgd = [{**example, "calls": [f"system.REQUEST('slot_{i}')"]} for i in range(args.n + 5)]
            results["check_actions_sgd_example"] = latencies(base, "/check-actions", sgd, warmup=5, key=keys["quiet"])
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
