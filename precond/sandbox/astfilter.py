"""Static checks on untrusted text before it is sent to the sandbox.

This is an extra layer, not the boundary: the fork server's audit hook, restricted builtins and OS
limits hold even when something passes here. Its job is to turn obvious escape attempts into clear,
cheap rejections, and to make proposed calls structured data rather than code.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import lru_cache

from precond.programs.checks import expression_hint
from precond.sandbox.child.values import clean
from precond.sandbox.types import ProgramError

BANNED_NAMES = frozenset({
    "exec", "eval", "compile", "open", "getattr", "setattr", "delattr", "globals", "locals", "vars",
    "__import__", "breakpoint", "input",
})
MAX_EXPRESSION_CHARS = 4000
MAX_IDENTIFIER_CHARS = 100
"""Longer names are refused: results carry action names (`Class.method`) bounded at 200 characters, and a
name cut there would no longer match the spec's."""


def _dunder(name: str) -> bool:
    return name.startswith("__")


def expression_problem(text: object, scope: str = "") -> str | None:
    """Why an assertion expression is refused, or None when it may be evaluated. `scope`: whose text it is."""
    if not isinstance(text, str):
        return "not a string"
    return _expression_problem(scope, text)


@lru_cache(maxsize=65536)
def _expression_problem(_scope: str, text: str) -> str | None:
    """Remembered per scope (a tenant), never by the text alone: the same assertions come back call after call
    (preconditions of every `check`), and an answer remembered for another tenant would tell, by its speed, that
    someone else sent this text."""
    if len(text) > MAX_EXPRESSION_CHARS:
        return f"longer than {MAX_EXPRESSION_CHARS} characters"
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        return f"not a single expression: {expression_hint(text) or clean(str(exc.msg))}"
    except (ValueError, MemoryError, RecursionError) as exc:  # null bytes, absurd nesting
        return f"not a single expression: {clean(str(exc))}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and (_dunder(node.id) or node.id in BANNED_NAMES):
            return f"disallowed name {clean(node.id, 80)!r}"
        if isinstance(node, ast.Attribute) and _dunder(node.attr):
            return f"disallowed attribute {clean(node.attr, 80)!r}"
        if isinstance(node, (ast.Yield, ast.YieldFrom, ast.Await)):
            return "disallowed construct (yield/await)"
    return None


@dataclass(frozen=True)
class ProposedCall:
    """`target.method(*args, **kwargs)` with literal arguments: data, never code."""

    text: str
    target: str
    method: str
    args: tuple[object, ...]
    kwargs: dict[str, object]


def parse_call(text: object) -> ProposedCall | str:
    """The structured call, or why it is refused."""
    if not isinstance(text, str):
        return "not a string"
    if len(text) > MAX_EXPRESSION_CHARS or "\n" in text.strip():
        return "not a single-line call"
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except (SyntaxError, ValueError):
        return "not a call expression"
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and isinstance(node.func.value, ast.Name)):
        return "not a call of the form name.method(...)"
    if _dunder(node.func.attr) or _dunder(node.func.value.id):
        return "disallowed name"
    try:
        args = tuple(ast.literal_eval(a) for a in node.args)
        kwargs = {k.arg: ast.literal_eval(k.value) for k in node.keywords if k.arg is not None}
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return "arguments must be literals"
    if len(kwargs) != len(node.keywords):
        return "arguments must be literals"
    return ProposedCall(text, node.func.value.id, node.func.attr, args, kwargs)


def check_program(source: object, where: str, index: int | None = None, scope: str = "") -> None:
    """Raise ProgramError for a program that does not parse or reaches for dunders other than __init__. `scope`:
    whose program it is (the tenant)."""
    if not isinstance(source, str):
        raise ProgramError(where, index, None, "TypeError", "program must be a string")
    problem = _program_problem(scope, source)
    if problem is not None:
        line, exc_type, message = problem
        raise ProgramError(where, index, line, exc_type, message)


@lru_cache(maxsize=1024)
def _program_problem(_scope: str, source: str) -> tuple[int | None, str, str] | None:
    """Remembered per scope (a tenant), as `_expression_problem`: the same spec is checked on every call, and reading
    a large spec takes long enough to be seen from outside."""
    try:
        tree = ast.parse(source)
    except SyntaxError as exc:
        return exc.lineno, "SyntaxError", clean(str(exc.msg))
    except (ValueError, MemoryError, RecursionError) as exc:
        return None, "SyntaxError", clean(str(exc))
    for node in ast.walk(tree):
        long = _identifier(node)
        if long is not None and len(long) > MAX_IDENTIFIER_CHARS:
            message = f"identifier {clean(long, 40)!r} is longer than {MAX_IDENTIFIER_CHARS} characters"
            return getattr(node, "lineno", None), "DisallowedConstruct", message
        name = None
        if isinstance(node, ast.Attribute) and _dunder(node.attr) and node.attr != "__init__":
            name = node.attr
        elif isinstance(node, ast.Name) and _dunder(node.id):
            name = node.id
        if name is not None:
            message = f"access to {clean(name, 80)!r} is not allowed"
            return getattr(node, "lineno", None), "DisallowedConstruct", message
    return None


def _identifier(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
        return node.name
    if isinstance(node, ast.arg):
        return node.arg
    return None
