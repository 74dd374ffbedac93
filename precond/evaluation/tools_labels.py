"""`precond eval tools --labels`: the tool-call guard scored on labelled calls, trained on half the tasks.

The tasks of `tau-airline/` are split in two halves (sorted task ids, alternately); rules are inferred model-free
from one half's successful runs (the demonstrations), with or without that half's labelled calls as the request's
`counterexamples` (`precond convert openai --labels`), and every labelled state-changing call of the other half is
judged on the history before it. Then the halves swap: every call is judged once, by rules that never saw its task
(split by task, never by call). In all, per split direction, per tool and per policy rule (T1-T8 of the data's
`tau-airline/LABELS.md`, beside its labels.json, not in this repository; a call counted under each rule its label
says it breaks, or keeps): unsafe_allow (calls labelled refused that the guard allows, over those calls) and
over_refuse (calls labelled allowed that it refuses, over those calls); and per refusal what it rests on
(`REASONS`), so that a refusal by a correlate with no counterexample behind it shows. Labels reach the request as
counterexamples only, never a demonstration or a prompt.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from precond.convert.labels import counterexamples, read_labels
from precond.convert.openai import Converted, Trajectory
from precond.evaluation.tools import NOW, WRITES, load
from precond_client.schemas import CheckRequest, InferRequest

RULE_NAMES = ("T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8")


@dataclass(frozen=True)
class Judged:
    task: str
    tool: str
    allowed: bool
    """The label."""
    broken: tuple[str, ...]
    """The rules the label says the call breaks."""
    kept: tuple[str, ...]
    """The rules the label says apply to the call and it keeps."""
    refused: bool
    """The guard's verdict."""
    reason: str = ""
    """What a refusal rests on (`reason_of`); empty for a call allowed."""


def halves(converted: Converted) -> tuple[set[str], set[str]]:
    tasks = sorted({_task(t) for t in converted.trajectories}, key=lambda t: (len(t), t))
    return set(tasks[0::2]), set(tasks[1::2])


def _task(trajectory: Trajectory | str) -> str:
    name = trajectory if isinstance(trajectory, str) else trajectory.name
    return name.split("-trial", 1)[0]


def infer_request(converted: Converted, records: list[dict[str, Any]], train: set[str], labelled: bool,
                  source: str) -> InferRequest:
    demos = [t for t in converted.trajectories if _task(t) in train and t.reward == 1.0]
    runs: list[dict[str, Any]] = []
    if labelled:
        mine = [r for r in records if f"task{r.get('task_id')}" in train]
        runs = counterexamples(converted, read_labels(mine, source, {t.name for t in converted.tools}), demos)
    return InferRequest.model_validate({
        "spec": converted.spec, "demonstrations": [t.program for t in demos],
        "actions": [f"AGENT.{w}" for w in WRITES], "counterexamples": runs,
        "options": {"generators": ["enumerate"], "candidates": "none", "now": NOW}})


REASONS = ("counterexample", "established", "assumed", "unseen", "other", "error")
"""What a refusal rests on: a violated rule that refuses a training call labelled refused (`counterexample`);
else the weakest violated rule's `decided` (`established`: the demonstrations show it; `assumed`: a possible
correlate; `unseen`: the placeholder `False` of an action with no rule learned, `options.unseen`); `other`
(transferred, zero-shot) or `error` (a rule or the call raised)."""


def reason_of(verdict: Any, refuses: dict[str, list[str]]) -> str:
    """The reason kind of a refused call's verdict, `refuses` being each rule's refused counterexamples."""
    if verdict.error:
        return "error"
    if any(refuses.get(rule) for rule in verdict.violations):
        return "counterexample"
    kinds = {verdict.decided.get(rule, "established") for rule in verdict.violations}
    return next((k for k in ("unseen", "assumed", "established") if k in kinds), "other")


def judge(engine: Any, converted: Converted, records: list[dict[str, Any]], test: set[str],
          inferred: Any) -> list[Judged]:
    """Every labelled call of the test tasks, on the history before it, by the `inferred` rules (an
    InferResponse: its rules, how each was decided and the counterexamples each refuses)."""
    rules: dict[str, list[str]] = inferred.preconditions
    decided = {a: {r: e.decided for r, e in inferred.evidence.get(a, {}).items() if e.decided} for a in rules}
    refuses = {r: list(e.refuses) for a in rules for r, e in inferred.evidence.get(a, {}).items()}
    runs = {t.name: t for t in converted.trajectories}
    judged = []
    for record in records:
        name = f"task{record['task_id']}-trial{record['trial']}"
        if _task(name) not in test:
            continue
        trajectory = runs[name]
        call = next(c for c, m in zip(trajectory.calls, trajectory.messages, strict=True)
                    if m == record["message_index"])
        lines = trajectory.program.splitlines()
        verdict = engine.check(CheckRequest(spec=converted.spec, preconditions=rules, decided=decided,
                                            history="\n".join(lines[: call.line]) + "\n",
                                            calls=[lines[call.line]])).results[0]
        said = record.get("rules") or {}
        broken, kept = (tuple(r for r in RULE_NAMES if said.get(r) is value) for value in (False, True))
        judged.append(Judged(_task(name), record["tool"], bool(record["allowed"]), broken, kept, not verdict.allowed,
                             "" if verdict.allowed else reason_of(verdict, refuses)))
    return judged


def scores(judged: Sequence[Judged]) -> dict[str, Any]:
    refused = [j for j in judged if not j.allowed]
    allowed = [j for j in judged if j.allowed]
    unsafe, over = sum(not j.refused for j in refused), sum(j.refused for j in allowed)
    return {"calls": len(judged), "labelled_refused": len(refused), "unsafe_allowed": unsafe,
            "labelled_allowed": len(allowed), "over_refused": over,
            "unsafe_allow": _share(unsafe, len(refused)), "over_refuse": _share(over, len(allowed))}


def _share(part: int, whole: int) -> float | None:
    return round(part / whole, 3) if whole else None


def run(engine: Any, data: Path, progress: Callable[[str], None]) -> dict[str, Any]:
    converted = load(data)
    source = str(data / "labels.json")
    records = json.loads((data / "labels.json").read_text(encoding="utf-8"))
    first, second = halves(converted)
    out: dict[str, Any] = {"halves": [sorted(first), sorted(second)]}
    for labelled in (False, True):
        judged: list[Judged] = []
        rules_of: list[dict[str, list[str]]] = []
        directions: list[dict[str, Any]] = []
        infer_s = judge_s = 0.0
        for train, test in ((first, second), (second, first)):
            started = time.perf_counter()
            inferred = engine.infer(infer_request(converted, records, train, labelled, source))
            infer_s += time.perf_counter() - started
            started = time.perf_counter()
            direction = judge(engine, converted, records, test, inferred)
            directions.append(scores(direction))
            judged += direction
            judge_s += time.perf_counter() - started
            rules_of.append(inferred.preconditions)
        mode = "with labels" if labelled else "without labels"
        out[mode] = {
            "total": scores(judged), "directions": directions, "rules": rules_of,
            "infer_s": round(infer_s, 2), "judge_s": round(judge_s, 2),
            "per_tool": {tool: scores([j for j in judged if j.tool == tool]) for tool in WRITES},
            "per_rule": {rule: {"unsafe_allowed": sum(not j.refused for j in judged if rule in j.broken),
                                "breaking": sum(rule in j.broken for j in judged),
                                "over_refused": sum(j.refused for j in judged if j.allowed and rule in j.kept),
                                "keeping": sum(rule in j.kept for j in judged if j.allowed)}
                         for rule in RULE_NAMES},
            "refusals": {kind: {"right": sum(j.reason == kind for j in judged if not j.allowed),
                                "over": sum(j.reason == kind for j in judged if j.allowed)}
                         for kind in REASONS if any(j.reason == kind for j in judged)},
        }
        total = out[mode]["total"]
        progress(f"{mode}: unsafe_allow {total['unsafe_allowed']}/{total['labelled_refused']} "
                 f"({total['unsafe_allow']}), over_refuse {total['over_refused']}/{total['labelled_allowed']} "
                 f"({total['over_refuse']}); infer {infer_s:.1f} s, judge {judge_s:.1f} s")
    return out


def table(result: dict[str, Any]) -> str:
    """Per tool, per split direction, per policy rule and per reason a refusal rests on, without and with
    labels side by side (markdown)."""
    plain, labelled = result["without labels"], result["with labels"]

    def cell(s: dict[str, Any], part: str, whole: str) -> str:
        return f"{s[part]}/{s[whole]}" if s[whole] else "-"

    lines = ["| tool | unsafe_allow without labels | with labels | over_refuse without labels | with labels |",
             "|---|---|---|---|---|"]
    for tool in [*WRITES, "total"]:
        a = plain["total"] if tool == "total" else plain["per_tool"][tool]
        b = labelled["total"] if tool == "total" else labelled["per_tool"][tool]
        lines.append(f"| {tool} | {cell(a, 'unsafe_allowed', 'labelled_refused')} | "
                     f"{cell(b, 'unsafe_allowed', 'labelled_refused')} | {cell(a, 'over_refused', 'labelled_allowed')}"
                     f" | {cell(b, 'over_refused', 'labelled_allowed')} |")
    lines += ["", "| trained on, judged on | unsafe_allow without labels | with labels | over_refuse without labels "
              "| with labels |", "|---|---|---|---|---|"]
    for k, name in enumerate(("first half, second", "second half, first")):
        a, b = plain["directions"][k], labelled["directions"][k]
        lines.append(f"| {name} | {cell(a, 'unsafe_allowed', 'labelled_refused')} | "
                     f"{cell(b, 'unsafe_allowed', 'labelled_refused')} | {cell(a, 'over_refused', 'labelled_allowed')}"
                     f" | {cell(b, 'over_refused', 'labelled_allowed')} |")
    lines += ["", "| policy rule | breaking calls allowed, without labels | with labels | keeping calls refused, "
              "without labels | with labels |", "|---|---|---|---|---|"]
    for rule in RULE_NAMES:
        a, b = plain["per_rule"][rule], labelled["per_rule"][rule]
        if a["breaking"] or a["keeping"]:
            lines.append(f"| {rule} | {cell(a, 'unsafe_allowed', 'breaking')} | {cell(b, 'unsafe_allowed', 'breaking')}"
                         f" | {cell(a, 'over_refused', 'keeping')} | {cell(b, 'over_refused', 'keeping')} |")
    lines += ["", "| a refusal rests on | calls labelled refused, without labels | with labels | calls labelled "
              "allowed, without labels | with labels |", "|---|---|---|---|---|"]
    for kind in REASONS:
        a, b = (m["refusals"].get(kind, {"right": 0, "over": 0}) for m in (plain, labelled))
        if a["right"] or a["over"] or b["right"] or b["over"]:
            lines.append(f"| {kind} | {a['right']} | {b['right']} | {a['over']} | {b['over']} |")
    return "\n".join(lines) + "\n"
