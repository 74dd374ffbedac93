"""`precond eval tools`: policy labels of tool calls, and the guard learned from successful runs judging them.

Runs on the tau-bench fixture (tests/fixtures/tau_airline/, five real trajectories) through the real engine
and sandbox; a failed run is edited so that it cancels a reservation it never read.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

from precond.engine.factory import build_engine
from precond.evaluation import tools
from precond.evaluation.cache import JsonCache
from precond_client.openai_log import Call

TAU = Path(__file__).resolve().parents[1] / "fixtures" / "tau_airline"
RESERVATION = {"reservation_id": "R1", "user_id": "u1", "cabin": "basic_economy", "insurance": "no",
               "created_at": "2024-05-01T10:00:00", "total_baggages": 2, "passengers": [{}, {}],
               "flights": [{"flight_number": "HAT1", "date": "2024-05-20"}]}


def known_after_read(reservation: dict[str, Any]) -> tools.Known:
    known = tools.Known()
    known.learn(Call("get_reservation_details", {"reservation_id": reservation["reservation_id"]}, 0,
                     reservation["reservation_id"], (True, reservation)))
    return known


def labels(tool: str, arguments: dict[str, Any], known: tools.Known) -> dict[str, bool]:
    call = Call(tool, arguments, 0)
    decided = {rule.name: rule.label(call, known) for rule in tools.RULES if tool in rule.tools}
    return {name: verdict for name, verdict in decided.items() if verdict is not None}


def test_labels_follow_the_policy_words() -> None:
    read = known_after_read(RESERVATION)
    assert labels("cancel_reservation", {"reservation_id": "R1"}, tools.Known()) == {"read before write": False}
    assert labels("cancel_reservation", {"reservation_id": "R1"}, read) == {
        "read before write": True, "cancellation allowed": False}  # basic economy, old, not insured
    insured = known_after_read(RESERVATION | {"insurance": "yes"})
    assert labels("cancel_reservation", {"reservation_id": "R1"}, insured)["cancellation allowed"] is True
    recent = known_after_read(RESERVATION | {"created_at": "2024-05-15T09:00:00"})
    assert labels("cancel_reservation", {"reservation_id": "R1"}, recent)["cancellation allowed"] is True
    same_flights = {"reservation_id": "R1", "cabin": "economy", "flights": RESERVATION["flights"]}
    assert labels("update_reservation_flights", same_flights, read)["basic economy flights unchanged"] is True
    other = same_flights | {"flights": [{"flight_number": "HAT2", "date": "2024-05-20"}]}
    assert labels("update_reservation_flights", other, read)["basic economy flights unchanged"] is False
    assert labels("update_reservation_baggages", {"reservation_id": "R1", "total_baggages": 1}, read)[
        "bags only added"] is False
    assert labels("update_reservation_passengers", {"reservation_id": "R1", "passengers": [{}]}, read)[
        "passenger count kept"] is False
    two_certificates = {"user_id": "u1", "passengers": [{}],
                        "payment_methods": [{"payment_id": "certificate_1"}, {"payment_id": "certificate_2"}]}
    assert labels("book_reservation", two_certificates, tools.Known())["booking limits and payment on file"] is False


def _cancel_without_reading(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The failed run (task 39), with the read of the reservation it cancels (and its result) removed."""
    edited = copy.deepcopy(records)
    traj = edited[3]["traj"]
    at = next(i for i, m in enumerate(traj) for c in m.get("tool_calls") or []
              if c["function"]["name"] == "get_reservation_details" and "H8Q05L" in c["function"]["arguments"])
    del traj[at: at + 2]
    return edited


def test_the_guard_from_successful_runs_refuses_a_write_without_its_read(tmp_path: Path) -> None:
    records = json.loads((TAU / "trajectories.json").read_text())
    (tmp_path / "trajectories.json").write_text(json.dumps(_cancel_without_reading(records)))
    (tmp_path / "tools.json").write_text((TAU / "tools.json").read_text())
    result = tools.run(build_engine(with_model=False), tmp_path, [tools.GuardConfig("marginal", 0.0)], print)
    (row,) = result["configs"]
    summary = row["summary"]
    assert result["demonstrations"] == 3 and result["without_writes"] == 1
    read = summary["per_rule"]["read before write"]
    assert all(read["learned"][t] for t in ("cancel_reservation", "update_reservation_flights",
                                            "update_reservation_baggages", "update_reservation_passengers"))
    assert (read["breaking"], read["refused_breaking"]) == (1, 1)  # the unread cancellation is refused
    assert summary["keeping"] == summary["allowed_keeping"] == 6
    assert summary["counterfactual"]["stopped_at_first_breaking_call"] == 1

    from precond.evaluation.tools_report import TOOLS_HEADING, write_tools_section  # matplotlib: only here

    store = JsonCache(tmp_path / "cache")
    store.put(result, "results", "tools")
    report = tmp_path / "results.md"
    report.write_text("# Evaluation results\n\n## Speed\n\nfast\n")
    write_tools_section(store, report)
    text = report.read_text()
    assert text.index(TOOLS_HEADING) < text.index("## Speed") and "| read before write |" in text
    assert (tmp_path / "img" / "tools_guard.png").stat().st_size > 0


def test_the_labels_score_says_per_direction_per_rule_and_per_reason_what_the_guard_did(tmp_path: Path) -> None:
    """`eval tools --labels` on the fixture runs, with labels written here: the two split directions add up to
    the total, a rule's over-refusals count the calls that keep it, and every refusal names what it rests on."""
    from precond.evaluation import tools_labels

    for name in ("trajectories.json", "tools.json"):
        (tmp_path / name).write_text((TAU / name).read_text())
    writes = {(5, 18): "update_reservation_passengers", (5, 20): "update_reservation_flights",
              (5, 22): "update_reservation_baggages", (30, 24): "cancel_reservation", (30, 30): "cancel_reservation",
              (15, 20): "update_reservation_flights", (39, 10): "cancel_reservation"}
    trials = {5: 1, 30: 1, 15: 2, 39: 1}
    records = [{"task_id": task, "trial": trials[task], "message_index": at, "tool": tool,
                "allowed": task != 39,
                "rules": {"T1": task != 39, "T4": True if tool == "cancel_reservation" else None}}
               for (task, at), tool in writes.items()]
    (tmp_path / "labels.json").write_text(json.dumps(records))
    result = tools_labels.run(build_engine(with_model=False), tmp_path, print)
    for mode in ("without labels", "with labels"):
        scored = result[mode]
        total, directions = scored["total"], scored["directions"]
        assert total["calls"] == len(records) == sum(d["calls"] for d in directions)
        assert total["over_refused"] == sum(d["over_refused"] for d in directions)
        assert scored["per_rule"]["T1"]["keeping"] == 6 and scored["per_rule"]["T4"]["keeping"] == 2
        assert scored["per_rule"]["T1"]["over_refused"] == total["over_refused"]
        refusals = scored["refusals"]
        assert set(refusals) <= set(tools_labels.REASONS)
        assert sum(r["over"] for r in refusals.values()) == total["over_refused"]
        assert sum(r["right"] for r in refusals.values()) == total["labelled_refused"] - total["unsafe_allowed"]
    assert result["without labels"]["refusals"]  # each half alone is too thin: its actions' rules refuse
    table = tools_labels.table(result)
    assert "| second half, first |" in table and "| a refusal rests on |" in table and "| T1 |" in table
