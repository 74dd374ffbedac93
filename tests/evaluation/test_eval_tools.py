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
from precond.evaluation.tools_report import TOOLS_HEADING, write_tools_section
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

    store = JsonCache(tmp_path / "cache")
    store.put(result, "results", "tools")
    report = tmp_path / "results.md"
    report.write_text("# Evaluation results\n\n## Speed\n\nfast\n")
    write_tools_section(store, report)
    text = report.read_text()
    assert text.index(TOOLS_HEADING) < text.index("## Speed") and "| read before write |" in text
    assert (tmp_path / "img" / "tools_guard.png").stat().st_size > 0
