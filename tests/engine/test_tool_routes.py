"""Every search of a conversation in the tool spec's state (`self.seen`, bounded) and the enumerator's condition
over it: each new segment of a flight change was listed by an earlier search or is among the reservation's own
flights. The condition is proposed from the demonstrations, run by the sandbox and by the embedded guard alike."""

from __future__ import annotations

import ast
import json
from collections import defaultdict
from typing import Any

from precond.convert.openai import convert
from precond.engine.candidates import tool_conditions, tool_facts
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.guard import AGENT_SHAPE
from precond_client.openai_log import AGENT_STATE, MAX_SEEN, AgentState, StateReader, converter_spec
from precond_client.rule_interpreter import Frame, Scope, compile_rule
from precond_client.schemas import InferOptions, InferRequest

TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string" if p in ("reservation_id", "origin", "destination", "date") else "array"}
                   for p in params}, "required": list(params)}}}
    for name, params in [("get_reservation_details", ("reservation_id",)),
                         ("search_direct_flight", ("origin", "destination", "date")),
                         ("search_onestop_flight", ("origin", "destination", "date")),
                         ("update_reservation_flights", ("reservation_id", "flights"))]]
PARAMS = ("reservation_id", "flights")
DIRECT = [{"flight_number": "HAT1", "origin": "JFK", "destination": "SEA"},
          {"flight_number": "HAT2", "origin": "JFK", "destination": "SEA"}]
ONESTOP = [[{"flight_number": "HAT3", "origin": "JFK", "destination": "ATL", "date": "2024-05-20"},
            {"flight_number": "HAT4", "origin": "ATL", "destination": "SEA", "date": "2024-05-20"}]]
ROUTE = ("reservation_id in self.results['get_reservation_details'] and all(x['flight_number'] in "
         "[y['flight_number'] for y in self.seen['search_direct_flight']] + "
         "[y['flight_number'] for y in self.seen['search_onestop_flight']] + "
         "[y['flight_number'] for y in self.results['get_reservation_details'][reservation_id]['flights']] "
         "for x in flights)")


def call(name: str, arguments: dict[str, Any], result: Any) -> list[dict[str, Any]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": name, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def change(new: list[str]) -> list[dict[str, Any]]:
    """The reservation read, the direct search (HAT1, HAT2), then the one-stop search (HAT3+HAT4), then a change
    to `new`: the direct search is no longer the last result of its kind only if searched again."""
    old = [{"flight_number": "HAT5", "date": "2024-05-20", "origin": "JFK", "destination": "ATL"},
           {"flight_number": "HAT6", "date": "2024-05-20", "origin": "ATL", "destination": "SEA"}]
    reservation = {"reservation_id": "R1", "origin": "JFK", "destination": "SEA", "flights": old}
    where = {"origin": "JFK", "destination": "SEA", "date": "2024-05-20"}
    return [{"role": "user", "content": "change my flight"},
            *call("get_reservation_details", {"reservation_id": "R1"}, reservation),
            *call("search_direct_flight", where, DIRECT),
            *call("search_direct_flight", {**where, "date": "2024-05-21"}, []),
            *call("search_onestop_flight", where, ONESTOP),
            *call("update_reservation_flights", {"reservation_id": "R1", "flights": [
                {"flight_number": n, "date": "2024-05-20"} for n in new]}, {})]


def test_every_search_is_kept_as_records_and_the_oldest_dropped_past_the_bound() -> None:
    state = AgentState(frozenset({"update_reservation_flights"}))
    state.result("search_direct_flight", None, True, DIRECT)
    state.result("search_direct_flight", None, True, [])
    state.result("search_onestop_flight", None, True, ONESTOP)
    assert state.results["search_direct_flight"] == {None: []}  # by key: the last only, as before
    assert state.seen["search_direct_flight"] == DIRECT
    assert state.seen["search_onestop_flight"] == ONESTOP[0]  # a connection's legs, flattened once
    state.result("update_reservation_flights", "R1", True, {"flights": []})
    assert "update_reservation_flights" not in state.seen  # a write's result is no read
    many = [{"flight_number": f"HAT{n}"} for n in range(MAX_SEEN + 5)]
    state.result("search_direct_flight", None, True, many)
    assert state.seen["search_direct_flight"] == many[5:]


def test_conversion_counts_the_trajectories_whose_searches_pass_the_bound() -> None:
    many = [{"flight_number": f"HAT{n}"} for n in range(MAX_SEEN)]
    where = {"origin": "JFK", "destination": "SEA", "date": "2024-05-20"}
    within = call("search_direct_flight", where, many)
    past = within + call("search_direct_flight", where, DIRECT)
    assert convert([change(["HAT1"]), within, past], TOOLS).past_seen == 1


def test_the_specs_state_keeps_what_agent_state_keeps() -> None:
    scope: dict[str, Any] = {"defaultdict": defaultdict, "WRITES": ()}
    exec(compile(AGENT_STATE, "AGENT_STATE", "exec"), scope)  # our own spec text, no caller input
    agent, mirror = scope["AGENT"](None), AgentState(frozenset())
    for value in (DIRECT, ONESTOP, {"reservation_id": "R1"}, "text", [{"flight_number": f"H{n}"} for n in range(300)]):
        agent.result("search_direct_flight", None, True, value)
        mirror.result("search_direct_flight", None, True, value)
        assert agent.seen == mirror.seen


def test_the_route_condition_is_proposed_run_by_the_sandbox_and_separates() -> None:
    runs = [change(["HAT1"]), change(["HAT3", "HAT4"])]
    converted = convert(runs, TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    atoms = tool_conditions.tool_atoms(facts, "update_reservation_flights", PARAMS)
    assert ROUTE in atoms
    with Sandbox(workers=1) as sandbox:
        judged = Engine(sandbox, None).infer(InferRequest(
            spec=converted.spec, demonstrations=[t.program for t in converted.trajectories],
            options=InferOptions(generators=["enumerate"], candidates="all")))
    report = {c.assertion: c for c in judged.candidates["AGENT.update_reservation_flights"]}[ROUTE]
    assert not report.reason.startswith("rejected"), report
    # the embedded guard reads the same state: the first search's flight holds, one never listed does not
    tools, writes = converter_spec(converted.spec)
    rule = compile_rule(ROUTE, Scope(AGENT_SHAPE, PARAMS))
    for new, expected in ((["HAT1"], True), (["HAT5", "HAT6"], True), (["HAT3", "HAT9"], False)):
        reader = StateReader(tools, writes, "history")
        messages = change(new)
        for index, message in enumerate(messages[:-2]):
            reader.message(index, message)
        arguments = json.loads(messages[-2]["tool_calls"][0]["function"]["arguments"])
        assert bool(rule(Frame(reader.state, [arguments["reservation_id"], arguments["flights"]]))) is expected


def test_the_route_kept_is_proposed_and_refuses_a_new_destination_or_an_open_round_trip() -> None:
    converted = convert([change(["HAT1"]), change(["HAT3", "HAT4"])], TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    atoms = tool_conditions.tool_atoms(facts, "update_reservation_flights", PARAMS)
    got = "self.results['get_reservation_details'][reservation_id]"
    found = (f"self.seen['search_direct_flight'] + self.seen['search_onestop_flight'] + {got}['flights'] "
             "if y['flight_number'] in [x['flight_number'] for x in flights]")
    read = "reservation_id in self.results['get_reservation_details']"
    ends = (f"{read} and {{y['destination'] for y in {found}}} - {{y['origin'] for y in {found}}} == "
            f"{{y['destination'] for y in {got}['flights']}} - {{y['origin'] for y in {got}['flights']}}")
    starts = (f"{read} and {{y['origin'] for y in {found}}} - {{y['destination'] for y in {found}}} == "
              f"{{y['origin'] for y in {got}['flights']}} - {{y['destination'] for y in {got}['flights']}}")
    assert ends in atoms and starts in atoms
    tools, writes = converter_spec(converted.spec)
    for rule, cases in ((ends, ((["HAT1"], True), (["HAT3", "HAT4"], True), (["HAT3"], False))),  # HAT3: to ATL
                        (starts, ((["HAT1"], True), (["HAT4"], False)))):  # HAT4 leaves ATL
        compiled = compile_rule(rule, Scope(AGENT_SHAPE, PARAMS))
        for new, expected in cases:
            reader = StateReader(tools, writes, "history")
            messages = change(new)
            for index, message in enumerate(messages[:-2]):
                reader.message(index, message)
            flights = json.loads(messages[-2]["tool_calls"][0]["function"]["arguments"])["flights"]
            assert bool(compiled(Frame(reader.state, ["R1", flights]))) is expected, (rule, new)
