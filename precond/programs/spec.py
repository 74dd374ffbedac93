"""What a spec declares: its classes' methods, which of them are stubs, and where a program's steps are."""

from __future__ import annotations

import ast
from dataclasses import dataclass

FunctionNode = ast.FunctionDef | ast.AsyncFunctionDef


@dataclass(frozen=True, eq=False)
class Method:
    """A method of a top-level spec class. Stubs (body only `pass`, `...` or a docstring) are the paper's
    action functions whose assertions are unknown; the other methods are observation functions."""

    cls: str
    name: str
    positional: tuple[str, ...]
    vararg: str | None
    kwonly: tuple[str, ...]
    kwarg: str | None
    stub: bool
    node: FunctionNode

    @property
    def qualname(self) -> str:
        return f"{self.cls}.{self.name}"

    @property
    def signature(self) -> tuple[str, ...]:
        """Every parameter after `self` as written (`*rest`, `**options`), for reports and prompts."""
        star = (f"*{self.vararg}",) if self.vararg else ()
        double = (f"**{self.kwarg}",) if self.kwarg else ()
        return (*self.positional, *star, *self.kwonly, *double)


def is_stub(node: FunctionNode) -> bool:
    return all(
        isinstance(stmt, ast.Pass)
        or (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant)
            and (stmt.value.value is Ellipsis or isinstance(stmt.value.value, str)))
        for stmt in node.body
    )


def _method(cls: str, node: FunctionNode) -> Method:
    a = node.args
    return Method(
        cls=cls, name=node.name,
        positional=tuple(x.arg for x in a.posonlyargs + a.args)[1:],
        vararg=a.vararg.arg if a.vararg else None,
        kwonly=tuple(x.arg for x in a.kwonlyargs),
        kwarg=a.kwarg.arg if a.kwarg else None,
        stub=is_stub(node), node=node,
    )


def read_methods(tree: ast.Module) -> dict[str, Method]:
    """Methods of the module's top-level classes by qualified name; names starting with `__` (dunders
    and name-mangled privates) are never actions or observations a program can call by name."""
    methods: dict[str, Method] = {}
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef) and not item.name.startswith("__"):
                    method = _method(node.name, item)
                    methods[method.qualname] = method
    return methods


def main_body(tree: ast.Module) -> list[ast.stmt]:
    """The steps of a trajectory. SGD style: the module body. ALFWorld style: the body of its single
    function (optionally followed by a bare call of it)."""
    body = tree.body
    if body and isinstance(body[0], ast.FunctionDef) and len(body) <= 2:
        fn = body[0]
        if len(body) == 1 or (
            isinstance(body[1], ast.Expr) and isinstance(body[1].value, ast.Call)
            and isinstance(body[1].value.func, ast.Name) and body[1].value.func.id == fn.name
            and not body[1].value.args
        ):
            return fn.body
    return body
