"""`ast.parse` one thread at a time, for the client's own reading of specs and rules.

CPython 3.11 keeps the AST constructor's recursion depth in the interpreter's state, which its threads share: two
threads parsing at once can end one parse with `SystemError: AST constructor recursion depth mismatch`
(python/cpython#106905). Agents guard calls from several threads (a framework's executor, a pool of tools), each
building a guard or compiling its rules, so every parse here takes one lock. A parse is a guard's set-up, never a
check's hot path.
"""

from __future__ import annotations

import ast
import threading

_LOCK = threading.Lock()


def parse_module(source: str) -> ast.Module:
    with _LOCK:
        return ast.parse(source)


def parse_expression(source: str) -> ast.Expression:
    with _LOCK:
        return ast.parse(source, mode="eval")
