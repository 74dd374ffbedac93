"""The enumerator's conditions over a tool-calling agent's state (precond/engine/candidates/tool_conditions.py), on
programs that
`precond/convert/openai.py` writes: reads bound to the call's own argument, result fields with the demonstrated
values, arguments against the result, disjunctions, and the bound on how many."""

from __future__ import annotations

import ast
import json

from precond.convert.openai import convert
from precond.engine.candidates import tool_conditions, tool_facts, tool_sources
from precond.engine.candidates.enumeration import StateModel, enumerate_atoms
from precond.engine.candidates.tool_relations import runnable
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond.sandbox.types import ActionInfo
from precond_client.schemas import InferOptions, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
    for name, params in [("get_reservation_details", ("reservation_id",)), ("cancel_reservation", ("reservation_id",)),
                         ("update_reservation_baggages", ("reservation_id", "total_baggages")),
                         ("update_reservation_passengers", ("reservation_id", "passengers"))]]
READ = "reservation_id in self.results['get_reservation_details']"
GOT = "self.results['get_reservation_details'][reservation_id]"


def run(rid: str, cabin: str, insured: str, bags: int, write: str, arguments: str) -> list[dict[str, object]]:
    result = (f'{{"reservation_id": "{rid}", "cabin": "{cabin}", "insurance": "{insured}", "total_baggages": {bags}, '
              '"passengers": [{"name": "A"}]}')
    return [{"role": "user", "content": "please"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_reservation_details",
                                                               "arguments": f'{{"reservation_id": "{rid}"}}'}}]},
            {"role": "tool", "content": result},
            {"role": "assistant", "tool_calls": [{"function": {"name": write, "arguments": arguments}}]},
            {"role": "tool", "content": "{}"}]


def atoms_for(runs: list[list[dict[str, object]]], action: str) -> list[str]:
    converted = convert(runs, TOOLS)
    spec = parse_spec(converted.spec)
    demos = [ast.parse(t.program) for t in converted.trajectories]
    params = spec.methods[f"AGENT.{action}"].positional
    info = ActionInfo(f"AGENT.{action}", params, True, (), ())
    return enumerate_atoms(StateModel(spec, demos), info, "AGENT").atoms


def test_reads_fields_and_disjunctions_of_the_same_reservation() -> None:
    runs = [run("A1", "business", "no", 1, "cancel_reservation", '{"reservation_id": "A1"}'),
            run("B2", "economy", "yes", 0, "cancel_reservation", '{"reservation_id": "B2"}'),
            run("C3", "business", "yes", 2, "cancel_reservation", '{"reservation_id": "C3"}')]
    atoms = atoms_for(runs, "cancel_reservation")
    assert READ in atoms
    assert f"{READ} and {GOT}['cabin'] != 'basic_economy'" not in atoms  # never shown: not proposed
    assert f"{READ} and {GOT}['cabin'] != 'economy'" in atoms
    assert f"{READ} and ({GOT}['cabin'] == 'business' or {GOT}['insurance'] == 'yes')" in atoms
    assert not any("self.results['cancel_reservation']" in a for a in atoms)  # a write's result is no read
    # a count is compared with a threshold or an argument, never with one value the logs show (a correlate)
    assert not any(f"{GOT}['total_baggages'] {op} " in a for a in atoms for op in ("==", "!="))
    assert f"{READ} and {GOT}['total_baggages'] >= 0" in atoms


def test_arguments_are_compared_with_the_field_of_the_same_name() -> None:
    bags = [run("A1", "economy", "no", 1, "update_reservation_baggages",
                '{"reservation_id": "A1", "total_baggages": 2}')]
    assert f"{READ} and total_baggages >= {GOT}['total_baggages']" in atoms_for(bags, "update_reservation_baggages")
    people = [run("A1", "economy", "no", 1, "update_reservation_passengers",
                  '{"reservation_id": "A1", "passengers": [{"name": "B"}]}')]
    assert f"{READ} and len(passengers) == len({GOT}['passengers'])" in atoms_for(
        people, "update_reservation_passengers")


def test_the_number_of_conditions_is_bounded() -> None:
    runs = [run(f"R{i}", f"cabin{i % 5}", ("yes", "no")[i % 2], i % 6, "cancel_reservation",
                f'{{"reservation_id": "R{i}"}}') for i in range(30)]
    converted = convert(runs, TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    assert len(tool_conditions.tool_atoms(facts, "cancel_reservation", ("reservation_id",))) <= \
        tool_conditions.MAX_ATOMS


def test_a_spec_without_the_result_observation_gets_none() -> None:
    spec = parse_spec("class SYSTEM:\n  def result(self, x): self.x = x\n  def act(self): pass\n")
    assert tool_facts.tool_class(spec) is None


FLIGHT_TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string" if p == "reservation_id" else "array"} for p in params},
    "required": list(params)}}}
    for name, params in [("get_reservation_details", ("reservation_id",)),
                         ("update_reservation_flights", ("reservation_id", "flights", "payment_methods"))]]


def flights_run(rid: str, created: str, dates: list[str], paid: list[str]) -> list[dict[str, object]]:
    flights = [{"flight_number": f"HAT{n}", "date": d} for n, d in enumerate(dates)]
    result = json.dumps({"reservation_id": rid, "created_at": created, "flights": flights,
                         "payment_methods": {p: {} for p in paid}})
    arguments = json.dumps({"reservation_id": rid, "flights": flights,
                            "payment_methods": [{"payment_id": p} for p in paid]})
    return [{"role": "assistant", "tool_calls": [{"function": {"name": "get_reservation_details",
                                                               "arguments": json.dumps({"reservation_id": rid})}}]},
            {"role": "tool", "content": result},
            {"role": "assistant", "tool_calls": [{"function": {"name": "update_reservation_flights",
                                                               "arguments": arguments}}]},
            {"role": "tool", "content": "{}"}]


def test_collections_dates_and_kinds_are_proposed_and_judged() -> None:
    runs = [flights_run("A1", "2024-05-14T20:00:00", ["2024-05-20"], ["certificate_1", "credit_card_2"]),
            flights_run("B2", "2024-05-01T10:00:00", ["2024-05-10", "2024-05-20"], ["gift_card_3"])]
    converted = convert(runs, FLIGHT_TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    params = ("reservation_id", "flights", "payment_methods")
    without_now = tool_conditions.tool_atoms(facts, "update_reservation_flights", params)
    pairs = "{(x['date'], x['flight_number']) for x in flights}"
    assert f"{READ} and {pairs} == {{(x['date'], x['flight_number']) for x in {GOT}['flights']}}" in without_now
    assert f"{READ} and all(x['payment_id'] in {GOT}['payment_methods'] for x in payment_methods)" in without_now
    assert "len([x for x in payment_methods if 'certificate_' in x['payment_id']]) <= 1" in without_now
    assert "len([x for x in payment_methods if 'gift_card_' in x['payment_id']]) <= 3" in without_now
    assert not any("2024-05-15" in a or "2024-05-14T15" in a for a in without_now)  # no `now`: none on it
    facts.now = "2024-05-15T15:00:00"
    with_now = tool_conditions.tool_atoms(facts, "update_reservation_flights", params)
    assert f"{READ} and {GOT}['created_at'] >= '2024-05-14T15:00:00'" in with_now
    assert f"{READ} and all(x['date'] >= '2024-05-15' for x in {GOT}['flights'])" in with_now
    with Sandbox(workers=1) as sandbox:  # the sandbox runs every one of these forms
        judged = Engine(sandbox, None).infer(InferRequest(
            spec=converted.spec, demonstrations=[t.program for t in converted.trajectories],
            options=InferOptions(generators=["enumerate"], now="2024-05-15T15:00:00", candidates="all")))
    reports = {c.assertion: c for c in judged.candidates["AGENT.update_reservation_flights"]}
    for atom in with_now:
        assert atom in reports and not reports[atom].reason.startswith("rejected"), (atom, reports.get(atom))


def test_labelled_calls_are_separated_by_what_a_policy_names_not_by_the_complement_of_one_value() -> None:
    atoms = [READ, f"{READ} and {GOT}['cabin'] != 'basic_economy'", f"{READ} and {GOT}['cabin'] == 'business'",
             f"{READ} and {GOT}['insurance'] != 'no'", f"{READ} and total_baggages != {GOT}['total_baggages']",
             f"{READ} and len(passengers) != len({GOT}['passengers'])"]
    assert tool_conditions.separating(atoms) == {
        READ, f"{READ} and {GOT}['cabin'] == 'business'", f"{READ} and total_baggages != {GOT}['total_baggages']",
        f"{READ} and len(passengers) != len({GOT}['passengers'])"}


def test_an_argument_listed_in_an_earlier_reads_record_is_the_callers_own() -> None:
    # every cancellation names a reservation the user's profile lists: "only the user's own reservations"
    tools = [*TOOLS, {"type": "function", "function": {"name": "get_user_details", "parameters": {
        "properties": {"user_id": {"type": "string"}}, "required": ["user_id"]}}}]

    def owner_run(uid: str, rid: str) -> list[dict[str, object]]:
        profile = json.dumps({"user_id": uid, "reservations": [rid, f"{rid}X"]})
        return [{"role": "user", "content": "cancel"},
                {"role": "assistant", "tool_calls": [{"function": {"name": "get_user_details",
                                                                   "arguments": json.dumps({"user_id": uid})}}]},
                {"role": "tool", "content": profile},
                *run(rid, "business", "no", 1, "cancel_reservation", json.dumps({"reservation_id": rid}))[1:]]

    converted = convert([owner_run(u, r) for u, r in (("u1", "A1"), ("u2", "B2"), ("u3", "C3"))], tools)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    owned = "any(reservation_id in y['reservations'] for y in self.seen['get_user_details'])"
    assert tool_sources.owned(facts, "cancel_reservation", ("self", "reservation_id")) == [owned]
    assert owned in tool_conditions.tool_atoms(facts, "cancel_reservation", ("self", "reservation_id"))
    assert runnable([owned], ("reservation_id",)) == [owned]  # the embedded guard runs it too
    stranger = convert([owner_run("u1", "A1"), [*owner_run("u2", "B2")[:3], *run(
        "Z9", "business", "no", 1, "cancel_reservation", json.dumps({"reservation_id": "Z9"}))[1:]]], tools)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in stranger.trajectories])
    assert tool_sources.owned(facts, "cancel_reservation", ("self", "reservation_id")) == []


def test_an_argument_that_is_a_field_of_a_record_a_search_listed_was_offered() -> None:
    # every move names a slot the search listed, though the argument is `new_slot` and the field `slot_id`
    tools = [{"type": "function", "function": {"name": name, "parameters": {
        "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
        for name, params in (("search_slots", ("day",)), ("move_visit", ("visit_id", "new_slot")))]

    def move(day: str, chosen: int) -> list[dict[str, object]]:
        slots = [{"slot_id": f"{day}-{h}", "hour": str(h)} for h in (9, 11, 15)]
        return [{"role": "user", "content": "move it"},
                {"role": "assistant", "tool_calls": [{"function": {"name": "search_slots",
                                                                   "arguments": json.dumps({"day": day})}}]},
                {"role": "tool", "content": json.dumps(slots)},
                {"role": "assistant", "tool_calls": [{"function": {"name": "move_visit", "arguments": json.dumps(
                    {"visit_id": f"V{day}", "new_slot": slots[chosen]["slot_id"]})}}]},
                {"role": "tool", "content": "{}"}]

    converted = convert([move("d1", 0), move("d2", 2), move("d3", 1)], tools)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    offered = "new_slot in [y['slot_id'] for y in self.seen['search_slots']]"
    assert tool_sources.offered(facts, "move_visit", ("self", "visit_id", "new_slot")) == [offered]
    assert runnable([offered], ("visit_id", "new_slot")) == [offered]
