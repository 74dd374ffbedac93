"""The model-free generator's own work is bounded: a 449-byte spec must not make the worker build millions of
candidates (issue 28, class 6: an action with 4 parameters and a pure query with 14 made 4^14 = 268 million
argument lists in the worker itself, outside every sandbox limit)."""

from __future__ import annotations

import ast

from engine.enumeration import MAX_QUERY_CALLS, StateModel, enumerate_atoms
from engine.spec import parse_spec
from sandbox.types import ActionInfo


def poison_spec(query_params: int) -> str:
    params = ", ".join(f"p{i}" for i in range(query_params))
    return ("class A:\n  def __init__(self):\n    self.x = 0\n"
            "  def act(self, a, b, c, d): self.x = a\n"
            f"  def q(self, {params}): return p0\n")


def atoms_for(query_params: int) -> list[str]:
    spec = parse_spec(poison_spec(query_params))
    demo = ast.parse("a = A()\na.act(1, 2, 3, 4)\n")
    info = ActionInfo("A.act", ("a", "b", "c", "d"), True, (), ((1, 2, 3, 4),))
    return enumerate_atoms(StateModel(spec, [demo]), info, "A")


def test_a_query_with_many_parameters_makes_a_bounded_number_of_candidates() -> None:
    # 4^10 = 1,048,576 argument lists (two atoms each) before the bound; small enough to show the old code's
    # product without taking the machine's memory, and the 14-parameter poison of the issue the same way.
    for query_params in (10, 14):
        queries = [a for a in atoms_for(query_params) if ".q(" in a]
        assert 0 < len(queries) <= 2 * MAX_QUERY_CALLS, (query_params, len(queries))


def test_a_small_query_still_gets_every_argument_list() -> None:
    queries = [a for a in atoms_for(2) if ".q(" in a]
    assert len(queries) == 2 * 4 ** 2  # every (action parameter, action parameter) pair, and its negation
