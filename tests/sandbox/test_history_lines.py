"""A history read line by line (precond/programs/lines.py, used by the warm child): the statements a whole parse gives,
or None, so that the whole text is parsed, whenever reading by lines could differ."""

from __future__ import annotations

import ast
from typing import Any

import pytest

from precond.programs.lines import LINE_BREAKS, line_statements


def remembered() -> Any:
    store: dict[object, Any] = {}

    def remember(key: object, build: Any) -> Any:
        if key not in store:
            store[key] = build()
        return store[key]

    return remember


def test_a_history_of_one_statement_a_line_reads_as_a_whole_parse_does() -> None:
    history = ("user = USER()\r\nsystem = SYSTEM(user)\n\n# a comment\nuser.INFORM('a\\x1cb')  # \x1c inside\r"
               "system.REQUEST('city'); system.REQUEST('date')\n  \nuser.INFORM_INTENT(x=[1, (2, 3)])\n")
    statements = line_statements(LINE_BREAKS.split(history), remembered())
    assert statements is not None
    assert [ast.dump(s, include_attributes=True) for s in statements] == [
        ast.dump(s, include_attributes=True) for s in ast.parse(history).body]


@pytest.mark.parametrize("history", [
    "x = [1,\n2]\n",  # a bracket over two lines
    "if a:\n    b()\n",  # a block
    "s = '''\nimport os\n'''\n",  # a string over three lines, whose middle line parses alone
    "x = 1 + \\\n2\n",  # a continuation
    "@dec\ndef f(): pass\n",  # a decorator
    "a = 1\nfrom __future__ import annotations\n",  # valid alone, not after a statement
])
def test_a_line_that_is_not_whole_statements_alone_makes_the_text_parse_whole(history: str) -> None:
    assert line_statements(LINE_BREAKS.split(history), remembered()) is None


def test_each_line_is_parsed_once_per_store() -> None:
    remember, calls = remembered(), []

    def counting(key: object, build: Any) -> Any:
        calls.append(key)
        return remember(key, build)

    turn = "user = USER()\nuser.INFORM('a')\n"
    first = line_statements(LINE_BREAKS.split(turn), counting)
    second = line_statements(LINE_BREAKS.split(turn + "user.INFORM('b')\n"), counting)
    assert first is not None and second is not None and second[:2] == first  # the same statements, kept
    assert len(calls) == 5 and len(set(calls)) == 3
