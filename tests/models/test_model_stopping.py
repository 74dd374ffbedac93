from __future__ import annotations

import pytest

from precond.engine.models.stopping import line_end, statement_end, stop_index


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (" x > 0\n        return", 6),
        (" x > 0", None),
        (" f(a,\n   b)\nnext", 11),
        (" [1,\n 2]", None),
        (" a and \\\n b\n", 11),
        (" s == '(' \n", 10),
        (' s == """a\n(b"""\n', 16),
        (" x  # (unclosed in a comment\nnext", 28),
        (" x; y = 1", 2),
        (" {'a': [1, (2,\n3)]}\n", 19),
        (" 'unterminated\n", 14),
        (" a \\", None),
    ],
)
def test_statement_end(text: str, expected: int | None) -> None:
    assert statement_end(text) == expected


def test_line_end_ignores_brackets() -> None:
    assert line_end(" f(a,\n b)") == 5
    assert line_end("user.INFORM('city')") is None


def test_stop_index_dispatches_on_rule() -> None:
    assert stop_index(" f(a,\n b)\n", "line") == 5
    assert stop_index(" f(a,\n b)\n", "statement") == 9
