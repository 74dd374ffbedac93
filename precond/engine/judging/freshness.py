"""Which state each observation writes, so a rule can be told to be *about* the latest news.

`ranking.enabling_rate` asks whether the observations since the agent's previous turn enabled an occurrence.
Turning a condition from false to true is one way; writing the very state it reads is the other: a success
notice follows a service result that said "success" again (`set_query_status(True)` after a booking, when the
search had already succeeded). Without the second reading the notice's rule is a phase, and the action is left
unguarded.

Both sides are read statically (the spec is never run here): an observation method writes `self.attr`,
`self.attr[key]` (the key a parameter, bound to the call's argument, or a literal) or calls a method on
`self.attr` (`self.seen.update(...)`); a condition reads the attributes it names and, for a literal or
parameter subscript, that key. A write matches a read of the same attribute when either key is unknown or
both are equal.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence

from precond.engine.spec import Spec
from precond.sandbox.types import Point, TraceResult

Access = tuple[str, object]  # attribute name, key (None: any key)
ANY = None


def _key(node: ast.expr, params: Sequence[str], args: Sequence[object]) -> object:
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name) and node.id in params:
        position = params.index(node.id)
        return args[position] if position < len(args) else ANY
    return ANY


def _self_attr(node: ast.expr) -> str | None:
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
        return node.attr
    return None


def _writes(method: ast.AST, params: Sequence[str], args: Sequence[object]) -> set[Access]:
    found: set[Access] = set()
    for node in ast.walk(method):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = list(node.targets)
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            targets = [node.target]
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            targets = [node.func.value]
        for target in targets:
            if isinstance(target, ast.Subscript) and (attr := _self_attr(target.value)):
                found.add((attr, _key(target.slice, params, args)))
            elif attr := _self_attr(target):
                found.add((attr, ANY))
    return found


def writes_at(spec: Spec, trace: TraceResult) -> dict[tuple[int, int], frozenset[Access]]:
    """(demonstration, position) -> what the observation there wrote; actions (stubs) write nothing."""
    out: dict[tuple[int, int], frozenset[Access]] = {}
    for name, info in trace.actions.items():
        method = spec.methods.get(name)
        if method is None or info.stub:
            continue
        for occ in info.occurrences:
            out[(occ.demo, occ.position)] = frozenset(_writes(method.node, method.positional, occ.args))
    return out


def reads(expression: str) -> frozenset[Access]:
    """The attributes (and literal keys) a condition reads; a parameter key reads any key."""
    try:
        tree = ast.parse(expression, mode="eval")
    except SyntaxError:
        return frozenset()
    found: set[Access] = set()
    keyed: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Attribute):
            key = node.slice.value if isinstance(node.slice, ast.Constant) else ANY
            found.add((node.value.attr, key))
            keyed.add(id(node.value))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and id(node) not in keyed:
            found.add((node.attr, ANY))
    return frozenset(found)


def refreshed(read: frozenset[Access], occ: Point, start: int,
              writes: Mapping[tuple[int, int], frozenset[Access]]) -> bool:
    """Whether an observation in [start, occ.position) of the occurrence's demonstration wrote what is read."""
    for position in range(start, occ.position):
        for attr, key in writes.get((occ.demo, position), ()):
            if any(attr == r and (key is ANY or rkey is ANY or key == rkey) for r, rkey in read):
                return True
    return False
