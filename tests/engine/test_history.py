"""Structured histories rendered to programs (precond/programs/history.py): literals only, checked against the spec."""

from __future__ import annotations

import ast
import json

import pytest

from precond.programs.checks import ProgramProblem
from precond.programs.history import render
from tests.engine.conftest import SHARED


def test_alfworld_actors_are_created_in_spec_order_and_bound_by_parameter_name() -> None:
    spec = json.loads((SHARED / "alfworld" / "demos.json").read_text())["spec_no_assertions"]
    program = render(spec, [{"actor": "agent", "act": "take", "args": ["apple 1", "fridge 1"]}])
    assert program.splitlines() == [
        "environment = Environment()", "agent = Agent(environment)", "agent.take('apple 1', 'fridge 1')"]


@pytest.mark.parametrize("typed", ["x'); import os; ('", "\\n__import__('os')", "'''", "{0.__class__}"])
def test_what_a_user_typed_is_one_string_literal(restaurants: dict[str, object], typed: str) -> None:
    program = render(str(restaurants["spec_program"]), [{"actor": "user", "act": "INFORM", "args": [typed]}])
    call = ast.parse(program).body[-1]
    assert isinstance(call, ast.Expr) and isinstance(call.value, ast.Call)
    assert [ast.literal_eval(a) for a in call.value.args] == [typed]


@pytest.mark.parametrize("value", [[1], {"a": 1}, float("nan")])
def test_arguments_other_than_scalars_are_refused(restaurants: dict[str, object], value: object) -> None:
    with pytest.raises(ProgramProblem) as refused:
        render(str(restaurants["spec_program"]), [{"actor": "user", "act": "INFORM", "args": [value]}])
    assert refused.value.problem.field == "history[0].args[0]"


def test_an_actor_and_act_are_read_as_python_reads_names(restaurants: dict[str, object]) -> None:
    """Python reads names NFKC-normalised (`ｕｓｅｒ` is `user`): an event is checked against the spec in that
    form, and what it renders is the spec's own name, whatever the letters it was sent in."""
    spec = str(restaurants["spec_program"])
    program = render(spec, [{"actor": "ｕｓｅｒ", "act": "ＩＮＦＯＲＭ", "args": ["city"]}])
    assert program.splitlines()[-1] == "user.INFORM('city')"
    with pytest.raises(ProgramProblem, match="unknown act"):
        render(spec, [{"actor": "user", "act": "＿＿init＿＿", "args": []}])
