"""`precond convert openai`: labels in the shapes users have them (by run index in a plain list of conversations,
or on the tool call itself), every tool guarded unless `--guard` says otherwise, `--writes` only saying which
tools change state, and labels past the request's bounds kept refusals first with the count said: never a
traceback. Input: the two domains written from scratch (tests/fixtures/tools_domains/)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond_client.schemas import MAX_COUNTEREXAMPLE_RUNS, InferRequest
from tests.cli.inprocess import ROOT, precond

DOMAINS = ROOT / "tests" / "fixtures" / "tools_domains"
CARD_WRITES = "freeze_card,unfreeze_card,replace_card,set_card_limit"


def convert(domain: str, out: Path, *options: str, trajectories: Path | None = None) -> Any:
    return precond("convert", "openai", str(trajectories or DOMAINS / domain / "trajectories.json"), "--tools",
                   str(DOMAINS / domain / "tools.json"), "--out", str(out), *options)


def request(out: Path) -> InferRequest:
    return InferRequest.model_validate_json((out / "request.json").read_text())


def labelled_lines(req: InferRequest) -> list[tuple[str, str]]:
    return [(req.demonstrations[run.demonstration].splitlines()[call.line - 1] if run.demonstration is not None
             else str(run.program).splitlines()[call.line - 1], call.verdict)
            for run in req.counterexamples for call in run.calls]


def test_every_tool_is_guarded_and_writes_only_say_what_changes_state(tmp_path: Path) -> None:
    done = convert("cards", tmp_path / "a", "--writes", CARD_WRITES)
    assert done.returncode == 0, done.stderr
    tools = [t["function"]["name"] for t in json.loads((DOMAINS / "cards" / "tools.json").read_text())]
    assert request(tmp_path / "a").actions == sorted(f"AGENT.{t}" for t in tools)  # reads guarded too
    spec = (tmp_path / "a" / "spec.py").read_text()
    assert "WRITES = ('freeze_card', 'replace_card', 'set_card_limit', 'unfreeze_card')" in spec
    done = convert("cards", tmp_path / "b", "--state-changing", CARD_WRITES, "--guard",
                   "get_card_details,freeze_card")
    assert done.returncode == 0, done.stderr
    assert request(tmp_path / "b").actions == ["AGENT.freeze_card", "AGENT.get_card_details"]
    assert (tmp_path / "b" / "spec.py").read_text() == spec  # the guarded choice does not change the spec
    done = convert("cards", tmp_path / "c", "--guard", "get_card_details,open_vault")
    assert done.returncode == 2 and "guarded tool 'open_vault' is not among the tools" in done.stderr
    done = convert("cards", tmp_path / "d", "--guard", " , ")
    assert done.returncode == 2 and "--guard: names no tool" in done.stderr


def test_labels_by_run_index_in_a_plain_list_of_conversations(tmp_path: Path) -> None:
    done = convert("cards", tmp_path / "out", "--writes", CARD_WRITES, "--labels",
                   str(DOMAINS / "cards" / "labels.json"))
    assert done.returncode == 0, done.stderr
    assert "labelled calls: 7 to refuse, 0 to allow, in 7 runs" in done.stderr
    lines = labelled_lines(request(tmp_path / "out"))
    assert ("agent.get_customer_profile('CU3')", "refuse") in lines  # a read before the caller was verified
    assert ("agent.list_card_transactions('K41')", "refuse") in lines  # another customer's card
    assert ("agent.set_card_limit('K11', 1500)", "refuse") in lines


def test_labels_on_the_calls_themselves(tmp_path: Path) -> None:
    done = convert("clinic", tmp_path / "out")
    assert done.returncode == 0, done.stderr
    assert "labelled calls: 7 to refuse, 0 to allow, in 7 runs" in done.stderr
    lines = labelled_lines(request(tmp_path / "out"))
    assert ("agent.get_patient_details('P300')", "refuse") in lines
    assert ("agent.cancel_appointment('A6', 'too_expensive')", "refuse") in lines


def test_a_label_on_a_call_that_is_no_verdict_exits_2_naming_it(tmp_path: Path) -> None:
    runs = json.loads((DOMAINS / "clinic" / "trajectories.json").read_text())
    at = next(i for i, m in enumerate(runs[11]) if "label" in (m.get("tool_calls") or [{}])[0])
    runs[11][at]["tool_calls"][0]["label"] = "maybe"
    (tmp_path / "t.json").write_text(json.dumps(runs))
    done = convert("clinic", tmp_path / "out", trajectories=tmp_path / "t.json")
    assert done.returncode == 2, done.stderr
    assert f"[11][{at}].tool_calls[0].label: expected 'refuse' or 'allow', found 'maybe'" in done.stderr


def test_labels_that_name_no_run_exit_2_naming_the_file_or_record(tmp_path: Path) -> None:
    cases = [([], "labels.json: names no run"),
             ([{"run": 18, "message_index": 3, "tool": "freeze_card", "allowed": False}],
              "labels.json: [0].run: no run 18: the trajectories file has 18"),
             ([{"message_index": 3, "tool": "freeze_card", "allowed": False}],
              "labels.json: [0]: names no run: needs run (its index), or task_id and trial"),
             ([{"run": 2, "message_index": 3, "tool": "freeze_card", "allowed": False}],
              "[0].message_index: 2 has no tool call at message 3"),
             ([{"run": 2, "message_index": 9, "tool": "lock_vault", "allowed": False}],
              "[0].tool: 'lock_vault' is not among the tools")]
    for labels, says in cases:
        (tmp_path / "labels.json").write_text(json.dumps(labels))
        done = convert("cards", tmp_path / "out", "--labels", str(tmp_path / "labels.json"))
        assert done.returncode == 2 and says in done.stderr, (labels, done.stderr)
        assert "Traceback" not in done.stderr


def test_more_labelled_runs_than_a_request_takes_keep_the_refusals_first(tmp_path: Path) -> None:
    runs = json.loads((DOMAINS / "cards" / "trajectories.json").read_text())
    labels = json.loads((DOMAINS / "cards" / "labels.json").read_text())
    good = [n for n in range(len(runs)) if n not in {label["run"] for label in labels}]
    copies, records = [], []
    for copy in range(15):  # 15 x 18 runs, each with a label: over the request's bound
        for n, run in enumerate(runs):
            changed = json.loads(json.dumps(run))
            changed[1]["content"] += f" (call {copy})"
            last = max(i for i, m in enumerate(changed) if m.get("tool_calls"))
            copies.append(changed)
            records.append({"run": len(copies) - 1, "message_index": last, "allowed": n in good,
                            "tool": changed[last]["tool_calls"][0]["function"]["name"]})
    (tmp_path / "t.json").write_text(json.dumps(copies))
    (tmp_path / "labels.json").write_text(json.dumps(records))
    done = convert("cards", tmp_path / "out", "--demos", "10", "--labels", str(tmp_path / "labels.json"),
                   trajectories=tmp_path / "t.json")
    assert done.returncode == 0, done.stderr
    assert f"{len(records) - MAX_COUNTEREXAMPLE_RUNS} labelled runs" in done.stderr and "left out" in done.stderr
    verdicts = [v for _, v in labelled_lines(request(tmp_path / "out"))]
    assert len(verdicts) == MAX_COUNTEREXAMPLE_RUNS and verdicts.count("refuse") == 15 * len(labels)
