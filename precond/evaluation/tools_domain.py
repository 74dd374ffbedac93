"""`precond eval tools --domain DIR`: the tool-call guard scored on a domain a user wrote from scratch.

A domain directory holds what a new user has (tests/fixtures/tools_domains/README.md): `tools.json`,
`trajectories.json` (a plain list of conversations or tau-bench records), labels (`labels.json` records and/or
`"label"` on the calls), optionally `writes.json` (the state-changing tools; default: named like writes) and a test
set written before any rule was learned: `test.json` (conversations, each ending with the call under test) with
`test_verdicts.json` (`{run, message_index, tool, allowed, rule}`). Rules are inferred model-free, every tool
guarded, from the runs that carry no refused label (the good runs), without labels and with them (the labelled
runs then travel as programs, the counterexamples); each test call is judged on the history before it. Then,
leave-one-run-out over the labelled runs: each labelled call is judged by rules learned from the good runs and
every other labelled run, so that a label that only teaches its own run shows. unsafe_allow: calls the policy
refuses that the guard allows, over those calls; over_refuse: calls it allows that the guard refuses. Labels and
verdicts never reach a prompt (the generator is model-free).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from precond.convert.labels import Label, counted, on_calls, read_labels
from precond.convert.openai import Converted, Trajectory, convert
from precond.evaluation.tools_labels import REASONS, Judged, reason_of, scores
from precond_client.schemas import CheckRequest, InferRequest, InferResponse


def _json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def load(domain: Path) -> tuple[Converted, list[Label], Converted, list[dict[str, Any]]]:
    """The training runs with their labels (on the calls and in `labels.json`), and the test set."""
    tools = _json(domain / "tools.json")
    writes = set(_json(domain / "writes.json")) if (domain / "writes.json").is_file() else None
    train = convert(_json(domain / "trajectories.json"), tools, "trajectories.json", "tools.json", writes)
    labels = on_calls(train)
    if (domain / "labels.json").is_file():
        labels += read_labels(_json(domain / "labels.json"), "labels.json", {t.name for t in train.tools},
                              [t.name for t in train.trajectories])
    test = convert(_json(domain / "test.json"), tools, "test.json", "tools.json", writes)
    return train, labels, test, _json(domain / "test_verdicts.json")


def infer_request(train: Converted, labels: Sequence[Label], taught: Sequence[Label]) -> InferRequest:
    """Demonstrations: the runs no label of the domain (`labels`) refuses a call of, the good runs, whichever
    labels teach; a labelled run is a failed one. `taught`: the labels given to the learner, whose runs travel as
    programs beside the demonstrations (none: learning from the good runs alone)."""
    refused = {label.run for label in labels if not label.allowed}
    demos = [t for t in train.trajectories if t.name not in refused and t.reward in (None, 1.0)]
    return InferRequest.model_validate({
        "spec": train.spec, "demonstrations": [t.program for t in demos],
        "actions": [f"AGENT.{t}" for t in sorted(train.guarded)], "counterexamples": counted(train, taught, demos).runs,
        "options": {"generators": ["enumerate"], "candidates": "none"}})


def judge_at(engine: Any, spec: str, trajectory: Trajectory, message: int, inferred: InferResponse,
             allowed: bool, task: str = "") -> Judged:
    """One call (the first at that message) on the history before it, by the inferred rules."""
    rules = inferred.preconditions
    decided = {a: {r: str(e.decided) for r, e in inferred.evidence.get(a, {}).items() if e.decided} for a in rules}
    refuses = {r: list(e.refuses) for a in rules for r, e in inferred.evidence.get(a, {}).items()}
    call = next(c for c, m in zip(trajectory.calls, trajectory.messages, strict=True) if m == message)
    lines = trajectory.program.splitlines()
    verdict = engine.check(CheckRequest(spec=spec, preconditions=rules, decided=decided,
                                        history="\n".join(lines[: call.line]) + "\n",
                                        calls=[lines[call.line]])).results[0]
    return Judged(task, call.tool, allowed, (), (), not verdict.allowed,
                  "" if verdict.allowed else reason_of(verdict, refuses))


def judge_test(engine: Any, test: Converted, verdicts: Sequence[dict[str, Any]],
               inferred: InferResponse) -> list[tuple[Judged, str]]:
    """Every test call with the policy rule its verdict names (empty for a call the policy allows)."""
    return [(judge_at(engine, test.spec, test.trajectories[v["run"]], v["message_index"], inferred,
                      bool(v["allowed"]), str(v.get("task", ""))), str(v.get("rule") or ""))
            for v in verdicts]


def summary(judged: Sequence[tuple[Judged, str]]) -> dict[str, Any]:
    calls = [j for j, _ in judged]
    rules, tools = sorted({rule for _, rule in judged if rule}), sorted({j.tool for j in calls})
    return {"total": scores(calls),
            "per_tool": {tool: scores([j for j in calls if j.tool == tool]) for tool in tools},
            "per_rule": {rule: scores([j for j, r in judged if r == rule]) for rule in rules},
            "refusals": {kind: {"right": sum(j.reason == kind for j in calls if not j.allowed),
                                "over": sum(j.reason == kind for j in calls if j.allowed)}
                         for kind in REASONS if any(j.reason == kind for j in calls)}}


def held_out_labels(engine: Any, train: Converted, labels: Sequence[Label]) -> dict[str, Any]:
    """Each labelled run left out in turn: its labelled calls judged by rules learned from the rest."""
    runs = {t.name: t for t in train.trajectories}
    judged = []
    for run in sorted({label.run for label in labels}):
        inferred = engine.infer(infer_request(train, labels, [label for label in labels if label.run != run]))
        judged += [judge_at(engine, train.spec, runs[run], label.message, inferred, label.allowed)
                   for label in labels if label.run == run]
    return scores(judged)


def run(engine: Any, domain: Path, progress: Callable[[str], None]) -> dict[str, Any]:
    train, labels, test, verdicts = load(domain)
    out: dict[str, Any] = {"domain": domain.name, "runs": len(train.trajectories), "labels": len(labels),
                           "test_calls": len(verdicts), "guarded": sorted(train.guarded)}
    for mode, given in (("without labels", []), ("with labels", list(labels))):
        started = time.perf_counter()
        inferred = engine.infer(infer_request(train, labels, given))
        infer_s = time.perf_counter() - started
        judged = judge_test(engine, test, verdicts, inferred)
        out[mode] = {**summary(judged), "rules": inferred.preconditions, "infer_s": round(infer_s, 2),
                     "misjudged": [{"run": v["run"], "tool": j.tool, "allowed": j.allowed, "rule": rule,
                                    "reason": j.reason} for (j, rule), v in zip(judged, verdicts, strict=True)
                                   if j.refused == j.allowed]}
        total = out[mode]["total"]
        progress(f"{domain.name} {mode}: unsafe {total['unsafe_allowed']}/{total['labelled_refused']}, "
                 f"over-refused {total['over_refused']}/{total['labelled_allowed']} (infer {infer_s:.1f} s)")
    if labels:
        out["labels left out one run at a time"] = held_out_labels(engine, train, labels)
    return out


def table(result: dict[str, Any]) -> str:
    """Per policy rule and per tool, without and with labels (markdown)."""
    plain, labelled = result["without labels"], result["with labels"]

    def cell(s: dict[str, Any] | None, part: str, whole: str) -> str:
        return f"{s[part]}/{s[whole]}" if s and s[whole] else "-"

    def row(name: str, a: dict[str, Any] | None, b: dict[str, Any] | None) -> str:
        return (f"| {name} | {cell(a, 'unsafe_allowed', 'labelled_refused')} | "
                f"{cell(b, 'unsafe_allowed', 'labelled_refused')} | {cell(a, 'over_refused', 'labelled_allowed')} | "
                f"{cell(b, 'over_refused', 'labelled_allowed')} |")

    lines = [f"{result['domain']}: {result['test_calls']} test calls; rules from {result['runs']} runs and "
             f"{result['labels']} labels", "",
             "| | unsafe allowed, without labels | with labels | good refused, without labels | with labels |",
             "|---|---|---|---|---|", row("total", plain["total"], labelled["total"])]
    lines += [row(rule, plain["per_rule"][rule], labelled["per_rule"].get(rule)) for rule in plain["per_rule"]]
    lines += [row(tool, plain["per_tool"][tool], labelled["per_tool"].get(tool)) for tool in plain["per_tool"]]
    held = result.get("labels left out one run at a time")
    if held:
        lines += ["", f"labels left out one run at a time: {held['unsafe_allowed']} of {held['labelled_refused']} "
                  f"refused calls allowed, {held['over_refused']} of {held['labelled_allowed']} allowed calls refused"]
    return "\n".join(lines) + "\n"
