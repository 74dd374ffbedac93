"""`precond check --batch`: many (history, call) pairs judged in one command, one verdict a line, as one check
each would answer; a pair the service would refuse exits 2 naming it."""

from __future__ import annotations

import json
from pathlib import Path

from precond.convert import openai as openai_converter
from tests.cli.inprocess import precond
from tests.cli.test_convert_openai import records, tools

READ = "reservation_id in self.results['get_reservation_details']"


def test_pairs_are_judged_in_one_command_and_a_bad_one_is_named(tmp_path: Path) -> None:
    converted = openai_converter.convert(records(), tools())
    (tmp_path / "spec.py").write_text(converted.spec)
    (tmp_path / "rules.json").write_text(json.dumps({"AGENT.cancel_reservation": [READ]}))
    run = records()[1]["traj"]  # task 30: reads reservations, then cancels two
    at = next(i for i, m in enumerate(run) if m.get("tool_calls")
              and m["tool_calls"][0]["function"]["name"] == "cancel_reservation")
    cancel = run[at]["tool_calls"][0]["function"]
    pairs = [{"history": run[:at], "call": cancel},  # after its read: allowed
             {"history": run[:2], "call": cancel},  # before any read: refused
             {"history": run[:at], "call": {"name": "cancel_reservation", "arguments": {"reservation_id": "NOPE"}}}]
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    done = precond("check", "--batch", str(tmp_path / "pairs.json"), "--spec", str(tmp_path / "spec.py"),
                   "--rules", str(tmp_path / "rules.json"))
    assert done.returncode == 0, done.stderr
    verdicts = [json.loads(line) for line in done.stdout.splitlines()]
    assert [v["allowed"] for v in verdicts] == [True, False, False]
    assert verdicts[1]["violations"] == [READ]
    (tmp_path / "pairs.json").write_text(json.dumps([pairs[0], {"history": run[:at], "call": {"name": "refund"}}]))
    done = precond("check", "--batch", str(tmp_path / "pairs.json"), "--spec", str(tmp_path / "spec.py"),
                   "--rules", str(tmp_path / "rules.json"))
    assert done.returncode == 2 and "pairs.json: [1]" in done.stderr and "refund" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_rules_from_an_infer_response_say_how_each_was_decided(tmp_path: Path) -> None:
    """An infer response as --rules: each verdict's rule_status comes from its evidence, as a single check's does
    (the placeholder `False` of an action no rule was learned for is 'missing', not 'given')."""
    converted = openai_converter.convert(records(), tools())
    (tmp_path / "spec.py").write_text(converted.spec)
    response = {"preconditions": {"AGENT.cancel_reservation": [READ], "AGENT.book_reservation": ["False"]},
                "evidence": {"AGENT.cancel_reservation": {READ: {"decided": "established"}},
                             "AGENT.book_reservation": {"False": {"decided": "unseen"}}}}
    (tmp_path / "rules.json").write_text(json.dumps(response))
    run = records()[1]["traj"]
    at = next(i for i, m in enumerate(run) if m.get("tool_calls")
              and m["tool_calls"][0]["function"]["name"] == "cancel_reservation")
    book = {"name": "book_reservation", "arguments": {"user_id": "u1", "origin": "JFK", "destination": "SEA",
                                                       "flight_type": "one_way", "cabin": "economy", "flights": [],
                                                       "passengers": [], "payment_methods": [],
                                                       "total_baggages": 0, "nonfree_baggages": 0,
                                                       "insurance": "no"}}
    pairs = [{"history": run[:at], "call": run[at]["tool_calls"][0]["function"]}, {"history": run[:at], "call": book}]
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    done = precond("check", "--batch", str(tmp_path / "pairs.json"), "--spec", str(tmp_path / "spec.py"),
                   "--rules", str(tmp_path / "rules.json"))
    assert done.returncode == 0, done.stderr
    verdicts = [json.loads(line) for line in done.stdout.splitlines()]
    assert [(v["allowed"], v["rule_status"]) for v in verdicts] == [(True, "established"), (False, "missing")]
