"""Learning a tool-call guard from the 120 airline runs and their labels, and judging the labelled calls in a batch.

    python bench/labels_bench.py [--data ../shared/data/tau-airline] [--json out.json]

Each step is the command a team would run, timed whole (start-up included), one after the other:
`precond convert openai --min-reward 1 --labels --guard <the six state-changing tools>` (the 53 successful runs
as demonstrations, the 133 labelled calls of the 120 runs as counterexamples; the labels are of those tools, and
the figures in docs were taken so), `precond infer` on that request (model-free: `enumerate`, with
policy.md's `now`), then `precond check --batch` on the 133 labelled calls (each the program before it and its
line) with the rules just inferred. Prints the seconds of each, the CPU and the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.evaluation.tools import NOW, WRITES, load  # noqa: E402

CLI = [sys.executable, "-m", "precond.cli"]


def timed(command: list[str], out: Path | None = None) -> float:
    started = time.perf_counter()
    with open(out, "w", encoding="utf-8") if out else open(os.devnull, "w") as sink:
        subprocess.run(command, check=True, stdout=sink, cwd=ROOT)
    return round(time.perf_counter() - started, 2)


def pairs(data: Path) -> list[dict[str, str]]:
    """Each labelled call as the program before it and its line (what `eval tools --labels` judges)."""
    converted = load(data)
    runs = {t.name: t for t in converted.trajectories}
    out = []
    for record in json.loads((data / "labels.json").read_text(encoding="utf-8")):
        trajectory = runs[f"task{record['task_id']}-trial{record['trial']}"]
        call = next(c for c, m in zip(trajectory.calls, trajectory.messages, strict=True)
                    if m == record["message_index"])
        lines = trajectory.program.splitlines()
        out.append({"history": "\n".join(lines[: call.line]) + "\n", "call": lines[call.line]})
    return out


def cpu() -> str:
    try:
        found = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        return next((line.split(":", 1)[1].strip() for line in found.splitlines() if line.startswith("Model name")),
                    platform.processor())
    except OSError:
        return platform.processor()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "tau-airline")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    data = args.data.resolve()
    results: dict[str, Any] = {"cpu": cpu(), "cores": os.cpu_count(), "load_before": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="labels-bench-") as name:
        work = Path(name)
        results["convert_s"] = timed([*CLI, "convert", "openai", str(data / "trajectories.json"), "--tools",
                                      str(data / "tools.json"), "--out", str(work), "--min-reward", "1",
                                      "--labels", str(data / "labels.json"), "--guard", ",".join(WRITES)])
        request = json.loads((work / "request.json").read_text(encoding="utf-8"))
        request["options"] = {"generators": ["enumerate"], "now": NOW, "candidates": "none"}
        (work / "request.json").write_text(json.dumps(request), encoding="utf-8")
        results["demonstrations"], results["labelled_runs"] = (len(request["demonstrations"]),
                                                               len(request["counterexamples"]))
        results["infer_s"] = timed([*CLI, "infer", str(work / "request.json")], work / "rules.json")
        batch = pairs(data)
        (work / "pairs.json").write_text(json.dumps(batch), encoding="utf-8")
        results["calls"] = len(batch)
        results["check_batch_s"] = timed([*CLI, "check", "--batch", str(work / "pairs.json"), "--spec",
                                          str(work / "spec.py"), "--rules", str(work / "rules.json")],
                                         work / "verdicts.jsonl")
        verdicts = (work / "verdicts.jsonl").read_text(encoding="utf-8").splitlines()
        results["verdicts"] = len(verdicts)
        results["refused"] = sum(not json.loads(v)["allowed"] for v in verdicts)
    results["load_after"] = os.getloadavg()
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
