"""Is this spec one a converter writes? Recognised from its structure, never from a flag the caller sets.

A check the gateway may judge itself (`precond.gateway.interpreted`) is one where nothing of the request is code
to run: the spec's observations must do exactly what the converter's do, so that the state a history builds can be
kept in Python without running the spec. Two shapes qualify:

* `precond convert openai`: the text must be, character for character, what the converter writes for the tools
  it declares (`precond_client.openai_log.converter_spec`, the embedded guard's own test).
* `precond convert sgd`: the module's `USER` class, `SYSTEM.__init__` and `SYSTEM.set_query_status` must be the
  converter's (compared as syntax trees, so a spec whose methods come in another order still qualifies), and every
  other method of `SYSTEM` a stub whose body is `pass`: one per SGD system act, with the act's one parameter, and
  any number of intents without parameters. An extra method, a decorator, a default, a statement in a body, an
  import beyond `defaultdict`'s: any of them and the spec is not this one.

`precond convert events` writes no spec of its own (it renders events over the user's spec): its programs are
judged here when that spec has one of these two shapes. Every other spec goes to the sandbox.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache

from precond.convert import sgd
from precond.programs import checks
from precond_client.openai_log import converter_spec


@dataclass(frozen=True)
class SGDSpec:
    """An SGD spec's syntax tree: what `interpreted` reads the objects' state and methods from."""

    user: ast.ClassDef
    system: ast.ClassDef


@dataclass(frozen=True)
class OpenAISpec:
    """A spec `precond convert openai` wrote: the embedded guard judges its checks."""


ConvertedSpec = SGDSpec | OpenAISpec


def _dump(node: ast.AST) -> str:
    return ast.dump(node, annotate_fields=False)


@lru_cache(maxsize=1)
def _sgd_reference() -> tuple[str, str, Mapping[str, str], str]:
    """The converter's own import, USER class, and SYSTEM's non-stub methods, as syntax-tree dumps."""
    tree = ast.parse(sgd.spec_program(sgd.Service("S", [], [])))
    imports, user, system = tree.body
    assert isinstance(system, ast.ClassDef)
    fixed = {item.name: _dump(item) for item in system.body
             if isinstance(item, ast.FunctionDef) and item.name in ("__init__", "set_query_status")}
    return _dump(imports), _dump(user), fixed, _dump(system)


def _act_parameter(act: str) -> str | None:
    return "slot" if act in sgd.SLOT_ACTS else "intent" if act in sgd.INTENT_ACTS else None


def _is_stub(node: ast.stmt, parameter: str | None) -> bool:
    """`def NAME(self[, parameter]): pass`, nothing else: no decorator, default, annotation or other statement."""
    if not isinstance(node, ast.FunctionDef) or node.decorator_list or node.returns:
        return False
    args = node.args
    wanted = ["self", *([parameter] if parameter else [])]
    plain = (not args.posonlyargs and not args.vararg and not args.kwonlyargs and not args.kwarg
             and not args.defaults and not args.kw_defaults)
    return (plain and [a.arg for a in args.args] == wanted and all(a.annotation is None for a in args.args)
            and len(node.body) == 1 and isinstance(node.body[0], ast.Pass))


def _system_matches(system: ast.ClassDef) -> bool:
    _, _, fixed, _ = _sgd_reference()
    if system.bases or system.keywords or system.decorator_list:
        return False
    seen: set[str] = set()
    for item in system.body:
        name = getattr(item, "name", None)
        if not isinstance(item, ast.FunctionDef) or name is None or name in seen:
            return False
        seen.add(name)
        if name in fixed:
            if _dump(item) != fixed[name]:
                return False
        elif name in sgd.SYSTEM_ACTS:
            if not _is_stub(item, _act_parameter(name)):
                return False
        elif name.startswith("_") or not _is_stub(item, None):
            return False
    return seen >= {*fixed, *sgd.SYSTEM_ACTS}


def _sgd_spec(tree: ast.Module) -> SGDSpec | None:
    imports, user_dump, _, _ = _sgd_reference()
    if len(tree.body) != 3:
        return None
    first, user, system = tree.body
    if _dump(first) != imports or not isinstance(user, ast.ClassDef) or _dump(user) != user_dump:
        return None
    if not isinstance(system, ast.ClassDef) or system.name != "SYSTEM" or not _system_matches(system):
        return None
    return SGDSpec(user, system)


def converted_spec(spec: str, scope: str) -> ConvertedSpec | None:
    """The converter shape of `spec`, or None for any other spec (`scope`: the caller's tag, under which the
    spec's reading is remembered). Parsed, never run."""
    try:
        tree, _ = checks.remembered_spec_methods(scope, spec)
    except (checks.ProgramProblem, RecursionError):
        return None
    if len(spec) > checks.REMEMBERED_SPEC_CHARS:
        return _sgd_spec(tree) or _openai_spec.__wrapped__(scope, spec)  # too large to keep
    return _sgd_spec(tree) or _openai_spec(scope, spec)


@lru_cache(maxsize=64)
def _openai_spec(_scope: str, spec: str) -> OpenAISpec | None:
    """Remembered per scope and text, as the spec's reading is (`checks.remembered_spec_methods`)."""
    try:
        converter_spec(spec)
    except ValueError:
        return None
    return OpenAISpec()
