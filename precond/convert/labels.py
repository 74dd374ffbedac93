"""Labelled tool calls → the counterexamples of an infer request (`precond convert openai --labels`).

A label names one call of a converted run and says whether the policy allows it. The run is named by tau-bench's
record names (`task_id` and `trial`) or by `run`: its index in the trajectories file (a plain list of
conversations) or its name; the call by the index of the assistant message that made it. A label may also sit on
the call itself (`"label": "refuse"` in the log, `precond.convert.openai`). A team has such labels from
incidents, reviews or the calls a supervisor undid. Each becomes a `LabelledCall` of its run: the run's program
line of that call, 'refuse' or 'allow'. A run that is a demonstration is named by its index (its labelled
'refuse' calls are then evidence against a rule, not for it); any other run travels as its program.

Input that names nothing (a file with no label, no call at that message index, a tool the tools do not have, a
call of another tool) or that contradicts itself (the same history and call labelled both ways) is refused, naming
the record(s): a silently dropped label would be a silently weaker guard. A request takes at most
MAX_COUNTEREXAMPLE_RUNS runs of labels: the runs that carry a refusal go first, and what is left out is counted
for the command to say. Standard library, the converter and the request's bounds only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any

from precond.convert.openai import Converted, Trajectory
from precond_client.openai_log import PlaceError
from precond_client.schemas import MAX_COUNTEREXAMPLE_RUNS, MAX_LABELLED_CALLS

SHAPE = "{run, message_index, tool, allowed} or {task_id, trial, message_index, tool, allowed}"


@dataclass(frozen=True)
class Label:
    run: str
    """The run's name as the converter gives it (`task3-trial0`, or `3` in a plain list of conversations)."""
    message: int
    tool: str
    allowed: bool
    where: str
    """`data/labels.json: [12]`, the file as it was given, for errors (the labelled call's name: `shown`)."""
    position: int = 0
    """Which call of that message (a label on the call itself knows; a record names the message's first)."""


def read_labels(data: Any, source: str, tools: set[str], runs: Sequence[str] = ()) -> list[Label]:
    """Records `{task_id, trial, ...}` or `{run, ...}` (docs/converting.md, "Labelled calls"), `runs` being the
    converted runs' names in the file's order (a `run` that is an integer is an index into them); the rest of a
    record is not read."""
    if not isinstance(data, list):
        raise PlaceError(source, f"expected a list of label records {SHAPE}")
    if not data:
        raise PlaceError(source, f"names no run: expected a list of label records {SHAPE}")
    labels = []
    for index, record in enumerate(data):
        where = f"{source}: [{index}]"
        if not isinstance(record, dict):
            raise PlaceError(where, f"expected an object {SHAPE}")
        message = record.get("message_index")
        if not isinstance(message, int) or isinstance(message, bool) or message < 0:
            raise PlaceError(f"{where}.message_index", "expected the index of the message that makes the call")
        tool = record.get("tool")
        if not isinstance(tool, str) or tool not in tools:
            raise PlaceError(f"{where}.tool", f"{tool!r} is not among the tools")
        allowed = record.get("allowed")
        if not isinstance(allowed, bool):
            raise PlaceError(f"{where}.allowed", "expected true or false")
        labels.append(Label(_run_name(record, where, runs), message, tool, allowed, where))
    return labels


def shown(where: str) -> str:
    """`labels.json: [12]` for `data/labels.json: [12]`: the labelled call's name, which reports and the review page
    show, names the file alone (a path as typed would show where it lay on the machine that converted it)."""
    file, separator, rest = where.partition(": ")
    return f"{PurePath(file).name}{separator}{rest}"


def _run_name(record: dict[str, Any], where: str, runs: Sequence[str]) -> str:
    if "run" in record:
        run = record["run"]
        if isinstance(run, int) and not isinstance(run, bool):
            if not 0 <= run < len(runs):
                raise PlaceError(f"{where}.run", f"no run {run}: the trajectories file has {len(runs)}")
            return runs[run]
        if isinstance(run, str):
            return run
        raise PlaceError(f"{where}.run", "expected the run's index in the trajectories file (or its name)")
    task, trial = record.get("task_id"), record.get("trial")
    if not isinstance(task, int | str) or not isinstance(trial, int | str) or isinstance(task, bool):
        raise PlaceError(where, "names no run: needs run (its index), or task_id and trial")
    return f"task{task}-trial{trial}"


def on_calls(converted: Converted) -> list[Label]:
    """The labels the logs carry on their calls, as records would name them."""
    labels = []
    for trajectory in converted.trajectories:
        for found in trajectory.labels:
            made = [c for c, n in zip(trajectory.calls, trajectory.messages, strict=True) if n == found.message]
            labels.append(Label(trajectory.name, found.message, made[found.position].tool, found.allowed,
                                found.where, found.position))
    return labels


@dataclass
class Counted:
    runs: list[dict[str, Any]]
    """The request's `counterexamples`."""
    skipped: int = 0
    """Labels of tools that are not the request's actions: checked, not written (no rule they could bear on)."""
    runs_left_out: int = 0
    calls_left_out: int = 0
    """Over the request's bounds (MAX_COUNTEREXAMPLE_RUNS, MAX_LABELLED_CALLS): refusals kept first."""


def counterexamples(converted: Converted, labels: Sequence[Label],
                    demonstrations: Sequence[Trajectory]) -> list[dict[str, Any]]:
    """The request's `counterexamples` (`counted`'s runs)."""
    return counted(converted, labels, demonstrations).runs


def counted(converted: Converted, labels: Sequence[Label], demonstrations: Sequence[Trajectory]) -> Counted:
    """Per labelled run, its labelled calls (demonstrations by index), every label checked first. A label of a
    tool that is not guarded (`--guard`) is checked like the others but not written. Over the request's bounds
    the runs that carry a refusal, and in a run its refusals, go first."""
    runs = {t.name: t for t in converted.trajectories}
    index = {t.name: i for i, t in enumerate(demonstrations)}
    seen: dict[str, Label] = {}
    calls: dict[str, list[dict[str, Any]]] = {}
    for label in labels:
        trajectory = runs.get(label.run)
        if trajectory is None:
            raise PlaceError(label.where, f"no run {label.run} among the trajectories")
        call, line = _call_at(trajectory, label)
        key = "\n".join(trajectory.program.splitlines()[: line + 1])
        other = seen.setdefault(key, label)
        if other.allowed != label.allowed:
            raise PlaceError(label.where, f"labels the same history and call as {other.where} the other way "
                             f"({call.tool} at message {label.message} of {label.run})")
        if other is label and label.tool in converted.guarded:
            calls.setdefault(label.run, []).append(
                {"line": line + 1, "verdict": "allow" if label.allowed else "refuse", "name": shown(label.where)})
    out = Counted([], skipped=sum(label.tool not in converted.guarded for label in labels))
    ordered = sorted(calls.items(), key=lambda item: not _refuses(item[1]))
    for name, labelled in ordered[:MAX_COUNTEREXAMPLE_RUNS]:
        kept = sorted(labelled, key=lambda c: c["verdict"] != "refuse")[:MAX_LABELLED_CALLS]
        out.calls_left_out += len(labelled) - len(kept)
        run: dict[str, Any] = ({"demonstration": index[name]} if name in index
                               else {"program": runs[name].program})
        out.runs.append({**run, "calls": sorted(kept, key=lambda c: c["line"])})
    out.runs_left_out = max(0, len(ordered) - MAX_COUNTEREXAMPLE_RUNS)
    out.calls_left_out += sum(len(labelled) for _, labelled in ordered[MAX_COUNTEREXAMPLE_RUNS:])
    return out


def _refuses(calls: Sequence[dict[str, Any]]) -> bool:
    return any(c["verdict"] == "refuse" for c in calls)


def _call_at(trajectory: Trajectory, label: Label) -> tuple[Any, int]:
    made = [call for call, n in zip(trajectory.calls, trajectory.messages, strict=True) if n == label.message]
    if len(made) <= label.position:
        raise PlaceError(f"{label.where}.message_index", f"{label.run} has no tool call at message {label.message}")
    call = made[label.position]
    if call.tool != label.tool:
        raise PlaceError(f"{label.where}.tool", f"the call at message {label.message} of {label.run} is "
                         f"{call.tool}, not {label.tool}")
    return call, call.line
