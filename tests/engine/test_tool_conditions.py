"""The enumerator's conditions over a tool-calling agent's state (precond/engine/tool_conditions.py), on programs that
`precond/convert/openai.py` writes: reads bound to the call's own argument, result fields with the demonstrated
values, arguments against the result, disjunctions, and the bound on how many."""

from __future__ import annotations

import ast

from precond.convert.openai import convert
from precond.engine import tool_conditions
from precond.engine.enumeration import StateModel, enumerate_atoms
from precond.engine.spec import parse_spec
from precond.sandbox.types import ActionInfo

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
    facts = tool_conditions.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    assert len(tool_conditions.tool_atoms(facts, "cancel_reservation", ("reservation_id",))) <= \
        tool_conditions.MAX_ATOMS


def test_a_spec_without_the_result_observation_gets_none() -> None:
    spec = parse_spec("class SYSTEM:\n  def result(self, x): self.x = x\n  def act(self): pass\n")
    assert tool_conditions.tool_class(spec) is None
