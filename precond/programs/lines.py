"""A history read line by line: a dialog's history is sent again with every turn, one line longer, so each line
is parsed once (per reader, remembered by its place and text) instead of the whole text at every request.

Reading line by line gives the statements a whole parse gives when every line is whole statements on its own:
a line that opens a block, a bracket, a string or a continuation does not parse alone, and then the text is
parsed whole. So does a `__future__` import, which is only valid at a module's start (alone, every line is).
"""

from __future__ import annotations

import ast
import functools
import re
import typing

LINE_BREAKS = re.compile(r"\r\n|\r|\n")
"""Where the parser starts a new line (`str.splitlines` also breaks at \x0b, \x0c, \x1c-\x1e, \x85, ...)."""

Remember = typing.Callable[[object, typing.Callable[[], typing.Any]], typing.Any]
"""`remember(key, build)`: `build()`, kept under `key` by the reader's own store (None is never kept)."""


MAX_LINES = 2000
"""Longer programs are parsed whole (a reader's store keeps a few thousand entries)."""


def line_statements(lines: typing.Sequence[str], remember: Remember) -> list[ast.stmt] | None:
    """The statements of the program whose lines (`LINE_BREAKS.split(source)`) these are, each line parsed on
    its own and remembered under its number and text; None when the text must be parsed whole (above)."""
    if len(lines) > MAX_LINES:
        return None
    statements: list[ast.stmt] = []
    for number, line in enumerate(lines, start=1):
        if not line or line.isspace():
            continue
        parsed = remember(("line statements", number, line), functools.partial(_alone, line, number))
        if parsed is None:
            return None
        statements.extend(parsed)
    return statements


def _alone(line: str, number: int) -> tuple[ast.stmt, ...] | None:
    try:
        tree = ast.parse(line)
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None
    if any(isinstance(node, ast.ImportFrom) and node.module == "__future__" for node in tree.body):
        return None
    ast.increment_lineno(tree, number - 1)
    return tuple(tree.body)
