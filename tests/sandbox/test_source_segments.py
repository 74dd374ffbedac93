"""The text of each statement of a program (precond/programs/lines.py `source_segments`, what a trace reports for
each step): the same as `ast.get_source_segment`, read off one split of the text for all the statements."""

from __future__ import annotations

import ast
from collections.abc import Callable

from hypothesis import given, settings
from hypothesis import strategies as st

from precond.programs.lines import source_segments

PIECES = st.sampled_from(["x = 1", "f('é\\u2028', 2)", "y = [1,\n 2]", "z = {'a':\r\n 'b'}", "if x:\n    y = 'ü'",
                          "s = '''a\rb'''", "t = ('\\x0c'\r 'q')", "u = 3; v = '日本'", "# note", "", "\x0c", " w = 4"])
BREAKS = st.sampled_from(["\n", "\r\n", "\r"])


def test_each_statements_text_is_what_get_source_segment_reads(examples: Callable[[int], int]) -> None:
    @settings(max_examples=examples(300), deadline=None)
    @given(st.lists(st.tuples(PIECES, BREAKS), max_size=8), st.booleans())
    def segments_are_get_source_segments(lines: list[tuple[str, str]], last_break: bool) -> None:
        source = "".join(piece + brk for piece, brk in lines)
        if not last_break:
            source = source.rstrip("\r\n")
        try:
            body = ast.parse(source).body
        except SyntaxError:
            return
        assert source_segments(source, body) == [ast.get_source_segment(source, s) for s in body]

    segments_are_get_source_segments()


def test_a_long_program_is_split_once() -> None:
    source = "\n".join(f"agent.result('t', {i}, True, {{'k': {'v' * 50!r}}})" for i in range(3000)) + "\n"
    body = ast.parse(source).body
    assert source_segments(source, body)[2999] == f"agent.result('t', 2999, True, {{'k': {'v' * 50!r}}})"
