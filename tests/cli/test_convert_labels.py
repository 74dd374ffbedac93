"""`precond convert openai --labels`: labelled calls become the request's counterexamples (a demonstration's by
its index, any other run's with its program); a label that names no call, a tool not in the tools, or the same
call labelled both ways exits 2 naming the record(s)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond_client.schemas import InferRequest
from tests.cli.inprocess import precond
from tests.cli.test_convert_openai import TAU

LABELS = [
    {"task_id": 30, "trial": 1, "message_index": 24, "tool": "cancel_reservation", "allowed": True},
    {"task_id": 39, "trial": 1, "message_index": 10, "tool": "cancel_reservation", "allowed": False},
    {"task_id": 5, "trial": 1, "message_index": 22, "tool": "update_reservation_baggages", "allowed": False},
]


def convert(tmp_path: Path, labels: list[dict[str, Any]]) -> Any:
    (tmp_path / "labels.json").write_text(json.dumps(labels))
    return precond("convert", "openai", str(TAU / "trajectories.json"), "--tools", str(TAU / "tools.json"),
                   "--out", str(tmp_path / "out"), "--min-reward", "1", "--labels", str(tmp_path / "labels.json"))


def test_labels_become_counterexamples_beside_the_demonstrations(tmp_path: Path) -> None:
    done = convert(tmp_path, LABELS)
    assert done.returncode == 0, done.stderr
    assert "labelled calls: 2 to refuse, 1 to allow, in 3 runs" in done.stderr
    request = InferRequest.model_validate_json((tmp_path / "out" / "request.json").read_text())
    assert len(request.demonstrations) == 3
    by_verdict = {(run.demonstration, run.program is not None): [(c.verdict, c.name) for c in run.calls]
                  for run in request.counterexamples}
    assert by_verdict[(None, True)] == [("refuse", "labels.json: [1]")]  # a failed run: its program
    assert str(tmp_path) not in json.dumps(request.model_dump()["counterexamples"])  # the file's name, not its path
    demonstrated = [run for run in request.counterexamples if run.demonstration is not None]
    assert len(demonstrated) == 2
    for run in demonstrated:  # each labelled line is the labelled call in that demonstration
        line = request.demonstrations[run.demonstration].splitlines()[run.calls[0].line - 1]
        assert line.startswith(("agent.cancel_reservation(", "agent.update_reservation_baggages(")), line
    assert "user.says" not in json.dumps([c.model_dump() for r in request.counterexamples for c in r.calls])


def test_a_label_naming_no_call_or_tool_exits_2_naming_the_record(tmp_path: Path) -> None:
    wrong_index = [{**LABELS[0], "message_index": 23}]
    done = convert(tmp_path, wrong_index)
    assert done.returncode == 2 and "[0].message_index: task30-trial1 has no tool call at message 23" in done.stderr
    done = convert(tmp_path, [LABELS[0], {**LABELS[1], "tool": "refund_everything"}])
    assert done.returncode == 2 and "[1].tool: 'refund_everything' is not among the tools" in done.stderr
    done = convert(tmp_path, [{**LABELS[1], "tool": "get_user_details"}])
    assert done.returncode == 2 and "is cancel_reservation, not get_user_details" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_same_call_labelled_both_ways_names_both_records(tmp_path: Path) -> None:
    done = convert(tmp_path, [*LABELS, {**LABELS[0], "allowed": False}])
    assert done.returncode == 2
    assert "[3]: labels the same history and call as" in done.stderr and "[0] the other way" in done.stderr


def test_labels_of_tools_that_are_not_guarded_are_left_out_and_counted(tmp_path: Path) -> None:
    (tmp_path / "labels.json").write_text(json.dumps(LABELS))
    done = precond("convert", "openai", str(TAU / "trajectories.json"), "--tools", str(TAU / "tools.json"),
                   "--out", str(tmp_path / "out"), "--guard", "cancel_reservation",
                   "--labels", str(tmp_path / "labels.json"))
    assert done.returncode == 0, done.stderr
    assert "labelled calls: 1 to refuse, 1 to allow" in done.stderr and "1 labels of tools that are not actions" \
        in done.stderr
    request = InferRequest.model_validate_json((tmp_path / "out" / "request.json").read_text())
    assert request.actions == ["AGENT.cancel_reservation"]
    assert sum(len(run.calls) for run in request.counterexamples) == 2
