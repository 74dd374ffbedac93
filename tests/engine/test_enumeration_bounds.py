"""The model-free generator's own work is bounded: a 449-byte spec must not make the worker build millions of
candidates (an action with 4 parameters and a pure query with 14 made 4^14 = 268 million
argument lists in the worker itself, outside every sandbox limit)."""

from __future__ import annotations

import ast

from precond.engine.candidates.enumeration import MAX_QUERY_CALLS, StateModel, enumerate_atoms
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.engine.work import COMPILE_POINTS
from precond.sandbox import Sandbox
from precond.sandbox.types import ActionInfo, Limits
from precond_client.schemas import InferRequest


def poison_spec(query_params: int) -> str:
    params = ", ".join(f"p{i}" for i in range(query_params))
    return ("class A:\n  def __init__(self):\n    self.x = 0\n"
            "  def act(self, a, b, c, d): self.x = a\n"
            f"  def q(self, {params}): return p0\n")


def atoms_for(query_params: int) -> list[str]:
    spec = parse_spec(poison_spec(query_params))
    demo = ast.parse("a = A()\na.act(1, 2, 3, 4)\n")
    info = ActionInfo("A.act", ("a", "b", "c", "d"), True, (), ((1, 2, 3, 4),))
    return enumerate_atoms(StateModel(spec, [demo]), info, "A").atoms


def test_a_query_with_many_parameters_makes_a_bounded_number_of_candidates() -> None:
    # 4^10 = 1,048,576 argument lists (two atoms each) before the bound; small enough to show the old code's
    # product without taking the machine's memory, and a 14-parameter poisoned spec the same way.
    for query_params in (10, 14):
        queries = [a for a in atoms_for(query_params) if ".q(" in a]
        assert 0 < len(queries) <= 2 * MAX_QUERY_CALLS, (query_params, len(queries))


def test_a_small_query_still_gets_every_argument_list() -> None:
    queries = [a for a in atoms_for(2) if ".q(" in a]
    assert len(queries) == 2 * 4 ** 2  # every (action parameter, action parameter) pair, and its negation


def wide_spec(attributes: int, params: int) -> str:
    """A spec whose size alone multiplies the enumerator's work: every scalar attribute makes 4 atoms and two
    more per action parameter (3,000 attributes and 20 parameters are 132,000 candidates from 60 KB)."""
    names = ", ".join(f"p{i}" for i in range(params))
    fields = "".join(f"    self.a{i} = 0\n" for i in range(attributes))
    return f"class A:\n  def __init__(self):\n{fields}  def act(self, {names}): self.a0 = p0\n"


def test_the_enumerator_stops_at_its_limit_without_building_the_rest() -> None:
    spec = parse_spec(wide_spec(3_000, 20))
    args = tuple(range(20))
    info = ActionInfo("A.act", tuple(f"p{i}" for i in range(20)), True, (), (args,))
    state = StateModel(spec, [ast.parse(f"a = A()\na.act{args}\n")])
    found = enumerate_atoms(state, info, "A", limit=500)
    assert len(found.atoms) == 500 and found.cut
    assert not enumerate_atoms(state, info, "A", limit=None).cut


def test_the_engine_spends_the_requests_work_budget_on_enumeration() -> None:
    """The same budget the gateway checks (PRECOND_MAX_WORK_POINTS) bounds the enumerator in the worker, and the
    answer says where it stopped. On the old code the action got all 132,000 candidates whatever the budget."""
    params = 20
    args = ", ".join(str(i) for i in range(params))
    request = InferRequest(spec=wide_spec(3_000, params), demonstrations=[f"a = A()\na.act({args})\n"],
                           actions=["A.act"], options={"generators": ["enumerate"], "candidates": "all"})
    budget = 100_000
    with Sandbox(Limits(max_points=budget), workers=1) as sandbox:
        response = Engine(sandbox, None).infer(request)
    n_points = 2 * 1  # two positions x one argument tuple
    judged = response.candidates["A.act"]
    assert 0 < len(judged) <= budget // (n_points + COMPILE_POINTS)
    warning = response.warnings["A.act"]
    assert "the enumerator stopped at" in warning and "PRECOND_MAX_WORK_POINTS" in warning
