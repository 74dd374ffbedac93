"""The tool-call guard learned from tau-bench retail's development runs and their labels, split by task.

    python bench/tool_retail_bench.py [--data ../shared/data/tau-retail] [--json out.json] [--skip-all] [--no-labels]

The 150 tasks are split in two halves (sorted ids, alternately). Rules are inferred model-free from one half's
successful runs, with that half's labelled policy-breaking runs as counterexamples (the labels of the calls
before and at each run's violating call), and every labelled state-changing call of the other half is judged on
the history before it; then the halves swap, so each call is judged once by rules that never saw its task.
Reports unsafe (calls labelled refused that the guard allows, over those calls) and over-refusal (calls labelled
allowed that it refuses, over those calls), per tool and per rule of tau-retail/LABELS.md (R1-R10), the rules, and the
inference's seconds; then (unless --skip-all) the seconds of one inference of all 150 runs with every label.
With --no-labels, the rules are inferred from the successful runs alone (no counterexamples): what the
demonstrations teach without a label.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.convert.labels import counterexamples, read_labels  # noqa: E402
from precond.convert.openai import Converted, convert  # noqa: E402
from precond.engine.factory import build_engine  # noqa: E402
from precond.evaluation.tools_labels import judge  # noqa: E402
from precond_client.schemas import InferRequest  # noqa: E402

WRITES = ("cancel_pending_order", "modify_pending_order_address", "modify_pending_order_items",
          "modify_pending_order_payment", "return_delivered_order_items", "exchange_delivered_order_items")
RULES = tuple(f"R{k}" for k in range(1, 11))


def task(name: str) -> str:
    return name.split("-trial", 1)[0]


def request(converted: Converted, records: list[dict[str, Any]], train: set[str] | None,
            labelled: bool = True) -> InferRequest:
    """The successful runs of `train` (None: all) and, where `labelled`, the labels of its policy-breaking runs."""
    demos = [t for t in converted.trajectories if t.reward == 1.0 and (train is None or task(t.name) in train)]
    mine = [r for r in records if r["trial"] != 0 and (train is None or f"task{r['task_id']}" in train)]
    runs = counterexamples(converted, read_labels(mine, "labels.json", {t.name for t in converted.tools}), demos) \
        if labelled else []
    return InferRequest.model_validate({
        "spec": converted.spec, "demonstrations": [t.program for t in demos], "actions": [f"AGENT.{w}" for w in WRITES],
        "counterexamples": runs, "options": {"generators": ["enumerate"], "candidates": "none"}})


def judged(engine: Any, converted: Converted, records: list[dict[str, Any]], test: set[str],
           inferred: Any) -> list[dict[str, Any]]:
    """Every labelled call of the `test` tasks judged by the rules (`eval tools --labels`' judge), with the
    rules of tau-retail/LABELS.md its label says it breaks."""
    mine = [r for r in records if f"task{r['task_id']}" in test]
    return [{"tool": j.tool, "allowed": j.allowed, "refused": j.refused,
             "broken": [r for r in RULES if (record.get("rules") or {}).get(r) is False]}
            for j, record in zip(judge(engine, converted, mine, test, inferred), mine, strict=True)]


def scores(calls: list[dict[str, Any]]) -> dict[str, Any]:
    bad = [c for c in calls if not c["allowed"]]
    good = [c for c in calls if c["allowed"]]
    unsafe, over = sum(not c["refused"] for c in bad), sum(c["refused"] for c in good)
    return {"unsafe": f"{unsafe}/{len(bad)}", "unsafe_rate": round(unsafe / len(bad), 3) if bad else None,
            "over_refused": f"{over}/{len(good)}", "over_rate": round(over / len(good), 3) if good else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "tau-retail")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--skip-all", action="store_true")
    parser.add_argument("--no-labels", action="store_true", help="infer from the successful runs alone")
    args = parser.parse_args()
    trajectories = json.loads((args.data / "trajectories.json").read_text(encoding="utf-8"))
    tools = json.loads((args.data / "tools.json").read_text(encoding="utf-8"))
    records = json.loads((args.data / "labels.json").read_text(encoding="utf-8"))
    converted = convert(trajectories, tools, "trajectories.json", "tools.json", set(WRITES))
    tasks = sorted({task(t.name) for t in converted.trajectories}, key=lambda t: (len(t), t))
    halves = (set(tasks[0::2]), set(tasks[1::2]))
    engine = build_engine(with_model=False)
    calls: list[dict[str, Any]] = []
    out: dict[str, Any] = {"rules": [], "infer_s": []}
    for train, test in ((halves[0], halves[1]), (halves[1], halves[0])):
        started = time.perf_counter()
        inferred = engine.infer(request(converted, records, train, not args.no_labels))
        out["infer_s"].append(round(time.perf_counter() - started, 1))
        out["rules"].append(inferred.preconditions)
        calls += judged(engine, converted, records, test, inferred)
        print(f"half: infer {out['infer_s'][-1]} s; {scores(calls)}", flush=True)
    out["total"] = scores(calls)
    out["per_tool"] = {w: scores([c for c in calls if c["tool"] == w]) for w in WRITES}
    out["per_rule"] = {r: scores([c for c in calls if r in c["broken"]]) for r in RULES}
    print(json.dumps({k: out[k] for k in ("total", "per_tool", "per_rule", "infer_s")}, indent=1), flush=True)
    if not args.skip_all:
        started = time.perf_counter()
        engine.infer(request(converted, records, None, not args.no_labels))
        out["all_150_infer_s"] = round(time.perf_counter() - started, 1)
        print(f"all 150 runs{'' if args.no_labels else ' with labels'}: infer {out['all_150_infer_s']} s", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
