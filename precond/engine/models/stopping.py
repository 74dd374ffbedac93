"""Where a completion ends, decided on text rather than tokens.

The engine asks for one line (a next action) or one Python statement (an `assert` whose condition may span
several lines inside brackets). Token boundaries do not line up with either: one token can hold ")\\n    ",
so the rules scan the decoded text and report the index to cut at.
"""

from __future__ import annotations

from typing import Literal

StopRule = Literal["statement", "line"]

_OPEN = "([{"
_CLOSE = ")]}"
_QUOTES = "\"'"


def line_end(text: str) -> int | None:
    index = text.find("\n")
    return None if index < 0 else index


def _string_end(text: str, start: int, quote: str) -> int | None:
    """Index just past the string literal whose opening `quote` ends at `start`; None if still open.

    A newline inside a one-quote string returns its index: the statement ends there (as a syntax error the
    caller's parse check will reject), rather than swallowing the following lines.
    """
    i = start
    while i < len(text):
        if text[i] == "\\":
            i += 2
        elif text.startswith(quote, i):
            return i + len(quote)
        elif text[i] == "\n" and len(quote) == 1:
            return i
        else:
            i += 1
    return None


def statement_end(text: str) -> int | None:
    """Index of the newline (or `;`) that ends the first statement of `text`, or None if it has not ended.

    A newline ends it unless it is inside brackets, a string, or follows a backslash continuation. Brackets
    inside strings and comments do not count. The scan starts at bracket depth 0: the text continues a
    suffix such as "        assert", which opens nothing.
    """
    depth = 0
    i = 0
    while i < len(text):
        char = text[i]
        if char in _QUOTES:
            quote = char * 3 if text.startswith(char * 3, i) else char
            end = _string_end(text, i + len(quote), quote)
            if end is None:
                return None
            i = end
            continue
        if char == "#":
            newline = text.find("\n", i)
            if newline < 0:
                return None
            i = newline
            continue
        if char == "\\" and text.startswith("\n", i + 1):
            i += 2
            continue
        if char in _OPEN:
            depth += 1
        elif char in _CLOSE:
            depth = max(0, depth - 1)
        elif char in "\n;" and depth == 0:
            return i
        i += 1
    return None


def stop_index(text: str, rule: StopRule) -> int | None:
    return line_end(text) if rule == "line" else statement_end(text)
