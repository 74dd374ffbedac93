"""The static pre-filter (an extra layer: the sandbox does not rely on it)."""

from __future__ import annotations

import pytest

from precond.sandbox import ProgramError
from precond.sandbox.astfilter import ProposedCall, check_program, expression_problem, parse_call


@pytest.mark.parametrize("expression", [
    "self.user.requested_slot[slot]", "not self.query_success", "'sink' in recep",
    "self.is_visible(recep)", "self.env.get_property(recep, 'open') == False",
    "all(x for x in self.items)",
])
def test_accepts_assertions(expression: str) -> None:
    assert expression_problem(expression) is None


@pytest.mark.parametrize("expression", [
    "x = 1", "a; b", "import os", "().__class__", "__import__('os')", "eval('1')", "open('/etc/passwd')",
    "getattr(self, 'x')", "self.__dict__", "lambda: (yield)", "(", "x" * 5000, "\x00",
])
def test_rejects(expression: str) -> None:
    assert expression_problem(expression) is not None


def test_parse_call() -> None:
    call = parse_call("agent.take('apple 1', 'fridge 1')")
    assert call == ProposedCall("agent.take('apple 1', 'fridge 1')", "agent", "take",
                                ("apple 1", "fridge 1"), {})
    assert isinstance(parse_call("system.REQUEST(slot='city')"), ProposedCall)
    for bad in ["f()", "a.b.c()", "a.b(x)", "a.__init__()", "a.b(*[1])", "a.b(1)\na.c(2)", "a.b"]:
        assert isinstance(parse_call(bad), str), bad


def test_check_program() -> None:
    check_program("class A:\n    def __init__(self):\n        super().__init__()\n", "spec")
    with pytest.raises(ProgramError) as caught:
        check_program("x = 1\ny = ().__class__\n", "demonstration", 3)
    assert (caught.value.index, caught.value.line) == (3, 2)
    with pytest.raises(ProgramError) as caught:
        check_program("def f(:\n", "spec")
    assert caught.value.exc_type == "SyntaxError" and caught.value.line == 1


def test_huge_identifier_is_refused() -> None:
    # Action names travel back from the sandbox bounded at 200 characters; a longer one would not match.
    for source in (f"class {'A' * 101}:\n    pass\n", f"x = {'b' * 101}\n", f"def f({'c' * 101}):\n    pass\n"):
        with pytest.raises(ProgramError, match="longer than 100 characters"):
            check_program(source, "spec")
    check_program(f"class {'A' * 100}:\n    pass\n", "spec")
