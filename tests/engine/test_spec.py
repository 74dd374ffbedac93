import ast
from typing import Any

import pytest

from engine.spec import action_header, observation_source, parse_spec, render_program, resolve_actions
from schemas.errors import InvalidProgram, UnknownAction


def test_default_actions_are_the_stub_methods(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    actions = resolve_actions(spec, None)
    assert actions == [f"SYSTEM.{a}" for a in restaurants["system_actions"]]  # type: ignore[union-attr]
    assert "SYSTEM.set_query_status" not in actions


def test_unknown_action_names_the_field(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    with pytest.raises(UnknownAction) as err:
        resolve_actions(spec, ["SYSTEM.INFORM", "SYSTEM.DANCE"])
    assert err.value.field == "actions[1]"


def test_syntax_error_reports_line() -> None:
    with pytest.raises(InvalidProgram, match="line 2"):
        parse_spec("class A:\n  def f(self) pass\n")


def test_prompt_parts_hide_action_stubs(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    source = observation_source(spec, resolve_actions(spec, None))
    assert "def INFORM(self, slot): pass" not in source and "def set_query_status" in source
    assert action_header(spec, "SYSTEM.INFORM") == "class SYSTEM:\n  def INFORM(self, slot):\n    assert"


def test_render_program_writes_assertions_that_parse(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    program = render_program(spec, {"SYSTEM.INFORM": ["self.user.requested_slot[slot]"],
                                     "SYSTEM.set_query_status": ["status in (True, False)"]})
    tree = ast.parse(program)
    system = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "SYSTEM")
    methods = {n.name: n for n in system.body if isinstance(n, ast.FunctionDef)}
    assert [ast.unparse(s) for s in methods["INFORM"].body] == ["assert self.user.requested_slot[slot]"]
    assert [type(s).__name__ for s in methods["set_query_status"].body] == ["Assert", "Assign"]
