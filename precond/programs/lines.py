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


def source_segments(source: str, nodes: typing.Sequence[ast.AST]) -> list[str | None]:
    """`ast.get_source_segment(source, node)` of each node, the text split once (`get_source_segment` splits all
    of it, character by character, for each node: quadratic in a long program's statements)."""
    parts = LINE_BREAKS.split(source)
    breaks = LINE_BREAKS.findall(source)
    lines = [part + brk for part, brk in zip(parts, breaks, strict=False)] + ([parts[-1]] if parts[-1] else [])
    return [_segment(lines, node) for node in nodes]


def _segment(lines: list[str], node: ast.AST) -> str | None:
    """`ast.get_source_segment` (unpadded) of one node over the text's lines, each with its line break."""
    lineno, end_lineno = getattr(node, "lineno", None), getattr(node, "end_lineno", None)
    col, end_col = getattr(node, "col_offset", None), getattr(node, "end_col_offset", None)
    if lineno is None or end_lineno is None or col is None or end_col is None:
        return None
    first, last = int(lineno) - 1, int(end_lineno) - 1
    col, end_col = int(col), int(end_col)
    if first == last:
        return lines[first].encode()[col:end_col].decode()
    return "".join([lines[first].encode()[col:].decode(), *lines[first + 1:last],
                    lines[last].encode()[:end_col].decode()])


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
