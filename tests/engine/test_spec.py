import ast
from typing import Any

import pytest

from precond.engine.candidates.prompting import KNOWN_RULES_CHARS, inference_suffix
from precond.engine.spec import (
    action_header,
    check_preconditions,
    observation_source,
    parse_spec,
    render_program,
    resolve_actions,
)
from precond_client.schemas.errors import InvalidProgram, UnknownAction


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


def test_the_known_rules_of_the_other_actions_come_before_the_asked_one(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    known = {"SYSTEM.NOTIFY_SUCCESS": ["self.query_success"], "SYSTEM.GOODBYE": [],
             "SYSTEM.NOTIFY_FAILURE": ["False"], "USER.INFORM": ["True"]}
    suffix = inference_suffix(spec, "SYSTEM.NOTIFY_FAILURE", known)
    # one class block: the siblings' rules, then the asked action's own (never its own known rule, never another
    # class's action, nothing for an action without rules)
    assert suffix == ("class SYSTEM:\n  def NOTIFY_SUCCESS(self):\n    assert self.query_success\n"
                      "  def NOTIFY_FAILURE(self):\n    assert")
    assert inference_suffix(spec, "SYSTEM.NOTIFY_FAILURE", {}) == action_header(spec, "SYSTEM.NOTIFY_FAILURE")


def test_the_known_rules_shown_are_bounded(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    known = {f"SYSTEM.{a}": [f"self.user.informed_slot['{'x' * 200}']"] * 3 for a in restaurants["system_actions"]}
    suffix = inference_suffix(spec, "SYSTEM.NOTIFY_FAILURE", known)
    assert KNOWN_RULES_CHARS // 2 < len(suffix) <= KNOWN_RULES_CHARS + len(action_header(spec, "SYSTEM.NOTIFY_FAILURE"))
    assert suffix.endswith("def NOTIFY_FAILURE(self):\n    assert")


def test_rules_that_passed_are_not_parsed_again_for_their_scope(restaurants: dict[str, Any],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    from precond.programs import checks

    parsed: list[str] = []
    real = checks.expression_problem

    def counted(text: str) -> str | None:
        parsed.append(text)
        return real(text)

    monkeypatch.setattr(checks, "expression_problem", counted)
    spec = str(restaurants["spec_program"])
    rules = {"SYSTEM.INFORM": ["self.user.requested_slot[slot]", "not self.user.no_more"]}
    for _ in range(3):
        check_preconditions(parse_spec(spec), {**rules}, "tenant-a")
    assert len(parsed) == 2  # the first check only
    check_preconditions(parse_spec(spec), {**rules}, "tenant-b")
    assert len(parsed) == 4  # another scope reads them itself
    check_preconditions(parse_spec(spec), {"SYSTEM.INFORM": [*rules["SYSTEM.INFORM"], "True"]}, "tenant-a")
    assert len(parsed) == 7  # other rules: read again


def test_rules_that_failed_fail_again_with_the_same_problem(restaurants: dict[str, Any]) -> None:
    spec = parse_spec(str(restaurants["spec_program"]))
    for rules, kind in (({"SYSTEM.INFORM": ["self.user.requested_slot[slot"]}, InvalidProgram),
                        ({"SYSTEM.DANCE": ["True"]}, UnknownAction)):
        messages = set()
        for _ in range(3):
            with pytest.raises(kind) as err:
                check_preconditions(spec, rules, "tenant-a")
            messages.add((str(err.value), err.value.field))
        assert len(messages) == 1, messages
