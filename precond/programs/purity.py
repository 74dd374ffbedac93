"""Which spec functions may change state, so that an assertion can be evaluated on a shared snapshot
instead of a deep copy. A wrong "pure" would let one evaluation change what the next one sees, so every
callee this analysis does not know counts as impure."""

from __future__ import annotations

import ast

_MUTATOR_NAMES = frozenset({
    "append", "add", "update", "pop", "popitem", "clear", "remove", "discard", "setdefault", "extend",
    "insert", "sort", "reverse", "appendleft", "extendleft", "popleft", "rotate", "send", "throw", "close",
    "write", "difference_update", "intersection_update", "symmetric_difference_update", "subtract",
})
_PURE_METHODS = frozenset({
    "get", "keys", "values", "items", "count", "index", "startswith", "endswith", "lower", "upper",
    "strip", "lstrip", "rstrip", "split", "rsplit", "find", "rfind", "join", "replace", "isdigit",
    "isalpha", "isalnum", "isspace", "islower", "isupper", "title", "capitalize", "casefold", "format",
    "issubset", "issuperset", "isdisjoint", "union", "intersection", "difference",
    "symmetric_difference", "copy", "most_common", "elements", "partition", "rpartition", "zfill",
    "isnumeric", "isdecimal", "isidentifier", "removeprefix", "removesuffix", "splitlines",
})
_PURE_FUNCTIONS = frozenset({
    "len", "any", "all", "isinstance", "issubclass", "sorted", "min", "max", "sum", "abs", "bool", "int",
    "str", "float", "list", "tuple", "set", "frozenset", "dict", "range", "enumerate", "zip", "reversed",
    "round", "repr", "hash", "callable", "type", "ord", "chr", "divmod", "pow", "format", "map", "filter",
})


class Purity:
    """Static guess of which spec functions may mutate state; a wrong 'pure' would break isolation, so any
    callee it does not know counts as impure."""

    def __init__(self, tree: ast.Module) -> None:
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        self.known = {f.name for f in functions}
        self.impure: set[str] = {f.name for f in functions if self._locally_impure(f)}
        calls = {id(f): self._callees(f) for f in functions}
        changed = True
        while changed:
            changed = False
            for f in functions:
                if f.name not in self.impure and calls[id(f)] & self.impure:
                    self.impure.add(f.name)
                    changed = True
        self.everything_slow = any(
            f.name in self.impure and (f.decorator_list or (f.name.startswith("__") and f.name != "__init__"))
            for f in functions
        )

    def expression_is_pure(self, node: ast.AST) -> bool:
        return not self.everything_slow and not self._locally_impure(node) and not (
            self._callees(node) & self.impure
        )

    def _callees(self, node: ast.AST) -> set[str]:
        names: set[str] = set()
        for sub in ast.walk(node):
            if isinstance(sub, ast.Call):
                if isinstance(sub.func, ast.Name):
                    names.add(sub.func.id)
                elif isinstance(sub.func, ast.Attribute):
                    names.add(sub.func.attr)
        return names

    def _locally_impure(self, node: ast.AST) -> bool:
        for sub in ast.walk(node):
            if isinstance(sub, (ast.AugAssign, ast.Delete, ast.Global, ast.Nonlocal, ast.Yield,
                                ast.YieldFrom, ast.Await)):
                return True
            if isinstance(sub, (ast.Assign, ast.AnnAssign)):
                targets = sub.targets if isinstance(sub, ast.Assign) else [sub.target]
                if any(isinstance(t, (ast.Attribute, ast.Subscript)) for tg in targets for t in ast.walk(tg)):
                    return True
            if isinstance(sub, ast.Attribute) and sub.attr in _MUTATOR_NAMES:
                return True
            if isinstance(sub, ast.Call) and not self._call_known(sub):
                return True
        return False

    def _call_known(self, call: ast.Call) -> bool:
        if isinstance(call.func, ast.Name):
            return call.func.id in _PURE_FUNCTIONS or call.func.id in self.known
        if isinstance(call.func, ast.Attribute):
            return call.func.attr in _PURE_METHODS or call.func.attr in self.known
        return False
