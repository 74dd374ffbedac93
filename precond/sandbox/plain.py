"""Which assertions may share a sandbox child with others.

Inside one child, an expression that can reach the interpreter's machinery (frames, globals, modules)
can rewrite the evaluator and so change other expressions' verdicts; the kernel cannot see that, because
it is all one process. So the worker sends only *plain* expressions together: they read the state through
attributes the spec itself defines, call a fixed set of side-effect-free builtins or the spec's own
methods, and name nothing but `self`, the action's parameters and what the spec itself defines at its top
level (classes, functions, constants; never an imported module). Everything else is
judged alone, in a child of its own, where tampering can change nothing but its own verdict.

This test runs in the worker, on text, before anything executes: untrusted code cannot switch it off.
Its only risk is a spec that itself defines introspection names as attributes; a spec is its caller's
own code and runs in that caller's child anyway.
"""

from __future__ import annotations

import ast
import builtins
from collections.abc import Collection
from dataclasses import dataclass
from functools import lru_cache

BUILTIN_NAMES = frozenset(dir(builtins))
SAFE_FUNCTIONS = frozenset({
    "len", "any", "all", "isinstance", "min", "max", "sum", "abs", "bool", "int", "str", "float", "list",
    "tuple", "set", "frozenset", "dict", "sorted", "range", "enumerate", "zip", "reversed", "round",
})
BUILTIN_METHODS = frozenset({
    "get", "keys", "values", "items", "count", "index", "startswith", "endswith", "lower", "upper", "strip",
    "lstrip", "rstrip", "split", "rsplit", "find", "rfind", "join", "replace", "isdigit", "isalpha",
    "isalnum", "isspace", "islower", "isupper", "title", "capitalize", "casefold", "issubset", "issuperset",
    "isdisjoint", "union", "intersection", "difference", "symmetric_difference", "most_common",
    "partition", "rpartition", "isnumeric", "isdecimal", "removeprefix", "removesuffix",
})
# Never plain, even where a spec defines them: the interpreter's introspection surface.
_INTROSPECTION_PREFIXES = ("_", "gi_", "cr_", "ag_", "f_", "tb_", "co_", "func_", "im_")
_INTROSPECTION_NAMES = frozenset({"mro", "format", "format_map", "fget", "fset", "fdel", "default_factory"})
_PLAIN_NODES = (
    ast.Expression, ast.BoolOp, ast.BinOp, ast.UnaryOp, ast.Compare, ast.IfExp, ast.Call, ast.keyword,
    ast.Constant, ast.Name, ast.Attribute, ast.Subscript, ast.Slice, ast.Tuple, ast.List, ast.Set, ast.Dict,
    ast.ListComp, ast.SetComp, ast.DictComp, ast.GeneratorExp, ast.comprehension, ast.JoinedStr,
    ast.FormattedValue, ast.expr_context, ast.boolop, ast.operator, ast.unaryop, ast.cmpop,
)


@dataclass(frozen=True)
class SpecVocabulary:
    """The names a plain expression may use, read from the spec's text."""

    attributes: frozenset[str]
    names: frozenset[str]
    """Names a plain expression may use besides `self` and the parameters: the spec's classes, and its
    top-level constants and functions (bound by assignment or `def`, never by `import`: a module is the way
    into the interpreter's machinery)."""
    imported: frozenset[str] = frozenset()
    """Names the spec binds by `import`: never plain. A name that is neither these nor a builtin can only
    raise NameError, so it is plain."""


def vocabulary(spec: str, scope: str = "") -> SpecVocabulary:
    """The names a plain expression over `spec` may use; remembered per scope (the tenant whose spec it is), never
    by the text alone: a spec read for another tenant would answer sooner, telling that someone sent it."""
    return _vocabulary(scope, spec)


@lru_cache(maxsize=256)
def _vocabulary(_scope: str, spec: str) -> SpecVocabulary:
    try:
        tree = ast.parse(spec)
    except (SyntaxError, ValueError, MemoryError, RecursionError):
        return SpecVocabulary(frozenset(), frozenset(), frozenset(BUILTIN_NAMES))
    imported = {(a.asname or a.name).partition(".")[0] for node in tree.body
                if isinstance(node, ast.Import | ast.ImportFrom) for a in node.names}
    attributes: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            attributes.add(node.attr)
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                    attributes.add(item.name)
                elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    attributes.add(item.target.id)
                elif isinstance(item, ast.Assign):
                    attributes.update(t.id for t in item.targets if isinstance(t, ast.Name))
    attributes = {a for a in attributes if not _introspection(a)}
    names = {n.name for n in tree.body if isinstance(n, ast.ClassDef | ast.FunctionDef)}
    for node in tree.body:
        targets = [node.target] if isinstance(node, ast.AnnAssign) else getattr(node, "targets", [])
        names.update(t.id for target in targets for t in ast.walk(target) if isinstance(t, ast.Name))
    names = {n for n in names - imported if not _introspection(n)}
    return SpecVocabulary(frozenset(attributes | BUILTIN_METHODS), frozenset(names), frozenset(imported))


def _introspection(name: str) -> bool:
    return name.startswith(_INTROSPECTION_PREFIXES) or name in _INTROSPECTION_NAMES


def is_plain(expression: str, params: Collection[str], words: SpecVocabulary) -> bool:
    try:
        tree = ast.parse(expression, mode="eval")
    except (SyntaxError, ValueError, MemoryError, RecursionError):
        return False
    bound = {t.id for c in ast.walk(tree) if isinstance(c, ast.comprehension)
             for t in ast.walk(c.target) if isinstance(t, ast.Name)}
    names = {"self", *params, *bound, *SAFE_FUNCTIONS, *words.names}
    for node in ast.walk(tree):
        if not isinstance(node, _PLAIN_NODES):
            return False
        if isinstance(node, ast.Name) and node.id not in names and (
                node.id in words.imported or node.id in BUILTIN_NAMES):
            return False
        if isinstance(node, ast.Attribute) and (node.attr not in words.attributes or _introspection(node.attr)):
            return False
        if isinstance(node, ast.keyword) and node.arg is None:
            return False
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in bound:
            return False
    return True
