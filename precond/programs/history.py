"""A history sent as structured events, rendered to a program over the spec; stdlib only, never executes.

`{"actor": "user", "act": "INFORM", "args": ["city"]}` becomes `user.INFORM('city')`. The actor is a spec
class's variable: the class name in lower case (`USER` → `user`, `Agent` → `agent`), created once at the
top in the spec's class order, each constructor parameter bound to an earlier actor of that name (or whose
name it begins: `env` → `environment`). Arguments become `repr` of a str, int, finite float, bool or None
only, so what an end user typed is a string literal whatever it says: it can never become code. Every event
is checked against the spec (known actor, known method, arity) and a bad one names its index: `history[3]`.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping, Sequence
from typing import Any

from precond.programs.checks import INVALID_INPUT, Problem, ProgramProblem, did_you_mean, remembered_spec_methods
from precond.programs.names import python_name
from precond.programs.spec import Method

SCALARS = (str, int, float, bool, type(None))


def _problem(field: str, message: str) -> ProgramProblem:
    return ProgramProblem(Problem(INVALID_INPUT, field, f"{field}: {message}"))


def _constructors(tree: ast.Module) -> dict[str, list[str] | None]:
    """Per top-level class, in order: its `__init__` parameters without defaults (after self), or None when
    its constructor takes `*args`/`**kwargs` or keyword-only parameters without defaults."""
    found: dict[str, list[str] | None] = {}
    for node in tree.body:
        if not isinstance(node, ast.ClassDef):
            continue
        params: list[str] | None = []
        for item in node.body:
            if isinstance(item, ast.FunctionDef) and item.name == "__init__":
                a = item.args
                positional = [x.arg for x in a.posonlyargs + a.args][1:]
                required = positional[: len(positional) - len(a.defaults)] if a.defaults else positional
                kwonly_required = [x.arg for x, d in zip(a.kwonlyargs, a.kw_defaults, strict=True) if d is None]
                params = None if (a.vararg or a.kwarg or kwonly_required) else required
        found[node.name] = params
    return found


def actors(tree: ast.Module) -> tuple[dict[str, str], list[str]]:
    """Actor variable → class, and the setup lines creating them (`user = USER()`, `system = SYSTEM(user)`).
    A class whose constructor needs something no earlier actor provides is not an actor."""
    made: dict[str, str] = {}
    setup: list[str] = []
    for cls, params in _constructors(tree).items():
        variable = python_name(cls.lower())  # the name Python binds: two classes may lower to one
        if params is None or variable in made or not variable.isidentifier():
            continue
        bound = []
        for param in params:
            match = param if param in made else next((v for v in made if v.startswith(param)), None)
            if match is None:
                break
            bound.append(match)
        else:
            made[variable] = cls
            setup.append(f"{variable} = {cls}({', '.join(bound)})")
    return made, setup


def _arity(method: Method, count: int) -> str | None:
    """Why `count` positional arguments do not fit the method, or None."""
    node = method.node.args
    total = len(method.positional)
    required = total - len(node.defaults)
    if count < required or (count > total and method.vararg is None):
        takes = f"{required}" if required == total else f"{required} to {total}"
        if method.vararg is not None:
            takes = f"at least {required}"
        names = ", ".join(method.signature) or "no arguments"
        return f"{method.qualname} takes {takes} argument(s) ({names}), got {count}"
    return None


def _literal(value: Any, field: str) -> str:
    if not isinstance(value, SCALARS):
        raise _problem(field, f"a {type(value).__name__} is not allowed; arguments are str, int, float, bool or null")
    if isinstance(value, float) and not math.isfinite(value):
        raise _problem(field, "only finite numbers are allowed")
    return repr(value)


def _literals(args: list[Any], field: str, index: int) -> str:
    """The arguments as literals, comma-separated; their field names are made only for an error."""
    try:
        return ", ".join([repr(value) if type(value) in _PLAIN_LITERALS else _literal(value, "") for value in args])
    except ProgramProblem:
        return ", ".join(_literal(value, f"{field}[{index}].args[{k}]") for k, value in enumerate(args))


_PLAIN_LITERALS = frozenset({str, int, bool, type(None)})
"""Types whose `repr` is a literal of the value as it is (a float is checked for being finite first)."""


def render(spec: str, events: Sequence[Mapping[str, Any]], field: str = "history", scope: str = "") -> str:
    """The program for a structured history; raises ProgramProblem naming `history[i]` for a bad event.
    `scope`: whose history it is (the spec's reading is remembered per scope: a dialog system sends the same
    spec with every check). A dialog repeats its few acts: each actor, act and number of arguments is checked
    once per history (40 events: 92 → 55 µs, both in one process)."""
    tree, methods = remembered_spec_methods(scope, spec)
    made, setup = actors(tree)
    lines = list(setup)
    calls: dict[tuple[Any, Any, int], str] = {}
    for index, event in enumerate(events):
        actor, act, args = event.get("actor"), event.get("act"), event.get("args", [])
        if not isinstance(args, list):
            event_call(made, methods, actor, act, None, f"{field}[{index}]")  # an unknown actor or act is said first
            raise _problem(f"{field}[{index}].args", "must be a list")
        key = (actor, act, len(args))
        call = calls.get(key) if isinstance(actor, str) and isinstance(act, str) else None
        if call is None:
            call = calls[key] = event_call(made, methods, actor, act, len(args), f"{field}[{index}]")
        lines.append(f"{call}({_literals(args, field, index)})")
    return "\n".join(lines) + "\n"


def event_call(made: Mapping[str, str], methods: Mapping[str, Method], actor: Any, act: Any, count: int | None,
          where: str) -> str:
    """`actor.method` for an event of `count` arguments (None: not checked); ProgramProblem naming `where` when
    it is not one."""
    actor = python_name(actor) if isinstance(actor, str) else actor
    act = python_name(act) if isinstance(act, str) else act
    if not isinstance(actor, str) or actor not in made:
        known = ", ".join(sorted(made)) or "none"
        hint = did_you_mean(str(actor), made) if isinstance(actor, str) else ""
        raise _problem(where, f"unknown actor {actor!r}{hint}; the actors of this spec are: {known}")
    cls = made[actor]
    method = methods.get(f"{cls}.{act}") if isinstance(act, str) else None
    if method is None or method.name.startswith("_"):
        own = sorted(m.name for m in methods.values() if m.cls == cls and not m.name.startswith("_"))
        hint = did_you_mean(str(act), own) if isinstance(act, str) else ""
        raise _problem(where, f"unknown act {act!r} of {actor} ({cls}){hint}; it has: {', '.join(own[:30])}")
    wrong = None if count is None else _arity(method, count)
    if wrong is not None:
        raise _problem(where, wrong)
    return f"{actor}.{method.name}"
