"""Labelled tool calls → the counterexamples of an infer request (`precond convert openai --labels`).

A label names one call of a converted run by the run (`task_id` and `trial`, tau-bench's record names) and the
index of the assistant message that made it, and says whether the policy allows it. A team has such labels from
incidents, reviews or the calls a supervisor undid. Each becomes a `LabelledCall` of its run: the run's program
line of that call, 'refuse' or 'allow'. A run that is a demonstration is named by its index (its labelled
'refuse' calls are then evidence against a rule, not for it); any other run travels as its program.

Input that names nothing (no call at that message index, a tool the tools do not have, a call of another tool)
or that contradicts itself (the same history and call labelled both ways) is refused, naming the record(s):
a silently dropped label would be a silently weaker guard. Standard library and the converter only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any

from precond.convert.openai import Converted, Trajectory
from precond_client.openai_log import PlaceError


@dataclass(frozen=True)
class Label:
    run: str
    """The run's name as the converter gives it (`task3-trial0`)."""
    message: int
    tool: str
    allowed: bool
    where: str
    """`data/labels.json: [12]`, the file as it was given, for errors."""
    name: str
    """`labels.json: [12]`, the file's name alone: the labelled call's name, which reports and the review page
    show (a path as typed would show where it lay on the machine that converted it)."""


def read_labels(data: Any, source: str, tools: set[str]) -> list[Label]:
    """Records `{task_id, trial, message_index, tool, allowed, ...}` (docs/converting.md, "Labelled calls"); the
    rest of a record is not read."""
    if not isinstance(data, list):
        raise PlaceError(source, "expected a list of label records")
    labels = []
    for index, record in enumerate(data):
        where = f"{source}: [{index}]"
        if not isinstance(record, dict):
            raise PlaceError(where, "expected an object {task_id, trial, message_index, tool, allowed}")
        task, trial = record.get("task_id"), record.get("trial")
        if not isinstance(task, int | str) or not isinstance(trial, int | str) or isinstance(task, bool):
            raise PlaceError(where, "needs task_id and trial (which run)")
        message = record.get("message_index")
        if not isinstance(message, int) or isinstance(message, bool) or message < 0:
            raise PlaceError(f"{where}.message_index", "expected the index of the message that makes the call")
        tool = record.get("tool")
        if not isinstance(tool, str) or tool not in tools:
            raise PlaceError(f"{where}.tool", f"{tool!r} is not among the tools")
        allowed = record.get("allowed")
        if not isinstance(allowed, bool):
            raise PlaceError(f"{where}.allowed", "expected true or false")
        labels.append(Label(f"task{task}-trial{trial}", message, tool, allowed, where,
                            f"{PurePath(source).name}: [{index}]"))
    return labels


def counterexamples(converted: Converted, labels: Sequence[Label],
                    demonstrations: Sequence[Trajectory]) -> list[dict[str, Any]]:
    """The request's `counterexamples`: per labelled run, its labelled calls (demonstrations by index). A label
    of a tool that is not one of the request's actions (not state-changing, or left out by `--writes`) is
    checked like the others but not written: the request infers no rule it could bear on (`skipped` counts)."""
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
        if other is label and label.tool in converted.writes:
            calls.setdefault(label.run, []).append(
                {"line": line + 1, "verdict": "allow" if label.allowed else "refuse", "name": label.name})
    out: list[dict[str, Any]] = []
    for name, labelled in calls.items():
        run: dict[str, Any] = ({"demonstration": index[name]} if name in index
                               else {"program": runs[name].program})
        out.append({**run, "calls": labelled})
    return out


def skipped(converted: Converted, labels: Sequence[Label]) -> int:
    """Labels of tools that are not the request's actions (`counterexamples` leaves them out)."""
    return sum(label.tool not in converted.writes for label in labels)


def _call_at(trajectory: Trajectory, label: Label) -> tuple[Any, int]:
    made = [(call, n) for call, n in zip(trajectory.calls, trajectory.messages, strict=True) if n == label.message]
    if not made:
        raise PlaceError(f"{label.where}.message_index", f"{label.run} has no tool call at message {label.message}")
    call = made[0][0]
    if call.tool != label.tool:
        raise PlaceError(f"{label.where}.tool", f"the call at message {label.message} of {label.run} is "
                         f"{call.tool}, not {label.tool}")
    return call, call.line
