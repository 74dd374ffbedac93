"""Candidates that cannot run on the spec's state: dropped and reported, never kept as a rule.

An action no demonstration calls has no point to judge a candidate at, so a model's guess that reads an
attribute the spec's state does not have (`self.reservation.cabin` where AGENT keeps `self.results`) passes
validation vacuously; kept, it would raise at every call and refuse everything with an error. Here each
candidate's `self.a.b` chains are read against the classes' attributes (what their methods assign, the classes
they link to, their methods): one that names an attribute the class does not have is rejected with the reason.
Static, over the spec's text; nothing runs.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import replace

from precond.engine.candidates.enumeration import StateModel
from precond.engine.spec import Spec
from precond.sandbox.types import EvaluateResult


def missing_attribute(expression: str, cls: str, state: StateModel, spec: Spec) -> str | None:
    """Why the expression raises on the state of `cls` (`AGENT has no attribute 'reservation'`), or None."""
    try:
        tree = ast.parse(expression, mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None  # the sandbox rejects it with its own reason
    for node in ast.walk(tree):
        chain = _chain(node) if isinstance(node, ast.Attribute) else None
        if chain is not None:
            owner: str | None = cls
            for name in chain:
                if owner is None:
                    break
                if not _has(state, spec, owner, name):
                    return f"{owner} has no attribute {name!r}"
                owner = state.shapes[owner].links.get(name) if owner in state.shapes else None
    return None


def _chain(node: ast.Attribute) -> list[str] | None:
    """`self.a.b` as ['a', 'b']; None when the chain does not start at `self`."""
    names: list[str] = []
    current: ast.expr = node
    while isinstance(current, ast.Attribute):
        names.append(current.attr)
        current = current.value
    return list(reversed(names)) if isinstance(current, ast.Name) and current.id == "self" else None


def _has(state: StateModel, spec: Spec, cls: str, name: str) -> bool:
    shape = state.shapes.get(cls)
    if shape is None:
        return True  # nothing known of it: the sandbox decides
    known = shape.scalars | shape.mappings | shape.collections | set(shape.links) | set(shape.queries)
    return name in known or any(m.cls == cls and m.name == name for m in spec.methods.values())


def drop_unrunnable(spec: Spec, state: StateModel, actions: Sequence[str], evaluated: EvaluateResult,
                    unseen: Mapping[str, bool]) -> tuple[EvaluateResult, dict[str, dict[str, str]]]:
    """The judged candidates of the actions no demonstration calls (`unseen`), those that raise on the spec's
    state rejected with the reason; and per action what was dropped, for its warning."""
    dropped: dict[str, dict[str, str]] = {}
    results = dict(evaluated.results)
    for action in actions:
        if not unseen.get(action):
            continue
        cls = spec.methods[action].cls
        kept = []
        for result in results.get(action, ()):
            why = missing_attribute(result.expression, cls, state, spec) if result.status != "rejected" else None
            if why is not None:
                reason = f"raises on the spec's state ({why}): dropped, never kept as a rule that refuses every call"
                dropped.setdefault(action, {})[result.expression] = why
                result = replace(result, status="rejected", reason=reason)
            kept.append(result)
        results[action] = tuple(kept)
    return EvaluateResult(evaluated.points, results), dropped
