"""The model-free generator: atoms over the state reachable from an action's `self` and its parameters.

The state's shape is read statically (attribute assignments in the spec, constructor wiring and call
arguments in the demonstrations); no atom needs to be right, because every one is validated and ranked
like a model candidate. What it buys is an answer in about a second with no model, and recall for
conditions a small model never writes.
"""

from __future__ import annotations

import ast
import itertools
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from precond.engine.candidates.tool_conditions import tool_atoms
from precond.engine.candidates.tool_facts import ToolFacts, read_facts, tool_class
from precond.engine.candidates.tool_relations import relations
from precond.engine.spec import Spec
from precond.programs import Method, Purity
from precond.sandbox.types import ActionInfo

MAX_KEYS = 40
MAX_CONSTANTS_PER_PARAM = 8
MAX_DEPTH = 2
MAX_QUERY_CALLS = 64
"""Argument lists tried per pure query: the choices multiply per parameter (4 action parameters and a query of
14 parameters are 4^14 = 268 million lists), and they are built here, in the worker, outside every sandbox
limit; so only the first lists of the product are made."""
MAPPING_FACTORIES = {"defaultdict", "dict", "OrderedDict", "Counter"}
SET_FACTORIES = {"set", "frozenset"}
SEQUENCE_FACTORIES = {"list", "tuple", "deque"}


@dataclass
class ClassShape:
    scalars: set[str] = field(default_factory=set)
    mappings: set[str] = field(default_factory=set)
    collections: set[str] = field(default_factory=set)
    links: dict[str, str] = field(default_factory=dict)  # attribute -> class name
    queries: dict[str, tuple[str, ...]] = field(default_factory=dict)  # pure method -> params


def _kind(value: ast.expr) -> str:
    if isinstance(value, ast.Dict | ast.DictComp):
        return "mapping"
    if isinstance(value, ast.Set | ast.SetComp | ast.List | ast.ListComp | ast.Tuple):
        return "collection"
    if isinstance(value, ast.Call) and isinstance(value.func, ast.Name):
        if value.func.id in MAPPING_FACTORIES:
            return "mapping"
        if value.func.id in SET_FACTORIES | SEQUENCE_FACTORIES:
            return "collection"
    return "scalar"


def _self_attribute(target: ast.expr) -> str | None:
    if isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name) and target.value.id == "self":
        return target.attr
    return None


def _returns_value(method: ast.AST) -> bool:
    return any(isinstance(node, ast.Return) and node.value is not None for node in ast.walk(method))


def _class_shape(cls: ast.ClassDef, methods: Iterable[Method], purity: Purity) -> tuple[ClassShape, dict[str, int]]:
    """Attribute kinds, plus which __init__ parameter (by position) each linked attribute comes from.

    Queries are the class's methods that return a value and write nothing (`programs.Purity`): safe and
    meaningful to call inside an assertion.
    """
    shape = ClassShape()
    for query in methods:
        if query.name not in purity.impure and _returns_value(query.node):
            shape.queries[query.name] = query.positional
    from_param: dict[str, int] = {}
    for method in (n for n in cls.body if isinstance(n, ast.FunctionDef)):
        params = [a.arg for a in method.args.args[1:]]
        for node in ast.walk(method):
            if not isinstance(node, ast.Assign):
                continue
            for target in node.targets:
                attr = _self_attribute(target)
                if attr is None:
                    continue
                value = node.value
                if method.name == "__init__" and isinstance(value, ast.Name) and value.id in params:
                    from_param[attr] = params.index(value.id)
                kind = _kind(value)
                {"mapping": shape.mappings, "collection": shape.collections}.get(kind, shape.scalars).add(attr)
    shape.scalars -= shape.mappings | shape.collections | set(from_param)
    return shape, from_param


def _literal(node: ast.expr) -> object:
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, RecursionError):
        return None


@dataclass
class DemoFacts:
    """What the demonstrations say statically: constructor wiring and constants passed per parameter name."""

    instance_class: dict[str, str] = field(default_factory=dict)
    constructor_args: dict[str, list[list[str | None]]] = field(default_factory=lambda: defaultdict(list))
    constants: dict[str, list[object]] = field(default_factory=lambda: defaultdict(list))


def _read_demos(spec: Spec, demos: Iterable[ast.Module]) -> DemoFacts:
    facts = DemoFacts()
    classes = {m.cls for m in spec.methods.values()}
    params_of = {(m.cls, m.name): m.positional for m in spec.methods.values()}
    for module in demos:
        for node in ast.walk(module):
            if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
                _note_constructor(node, classes, facts)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                _note_constants(node, facts, params_of)
    return facts


def _note_constructor(node: ast.Assign, classes: set[str], facts: DemoFacts) -> None:
    call = node.value
    assert isinstance(call, ast.Call)
    if not (isinstance(call.func, ast.Name) and call.func.id in classes):
        return
    for target in node.targets:
        if isinstance(target, ast.Name):
            facts.instance_class[target.id] = call.func.id
    names = [a.id if isinstance(a, ast.Name) else None for a in call.args]
    facts.constructor_args[call.func.id].append(names)


def _note_constants(call: ast.Call, facts: DemoFacts, params_of: dict[tuple[str, str], tuple[str, ...]]) -> None:
    assert isinstance(call.func, ast.Attribute)
    receiver = call.func.value
    cls = facts.instance_class.get(receiver.id) if isinstance(receiver, ast.Name) else None
    params = params_of.get((cls or "", call.func.attr))
    if params is None:
        return
    for name, arg in zip(params, call.args, strict=False):
        value = _literal(arg)
        if isinstance(value, str | int | float | bool) and value not in facts.constants[name]:
            facts.constants[name].append(value)


class StateModel:
    """Class shapes linked into a graph, so paths like `self.user.informed_slot` can be enumerated."""

    def __init__(self, spec: Spec, demos: Sequence[ast.Module]) -> None:
        self.facts = _read_demos(spec, demos)
        self.tool_class = tool_class(spec)
        self.tool_facts = read_facts(spec, self.tool_class, demos) if self.tool_class else ToolFacts()
        self.shapes: dict[str, ClassShape] = {}
        self.mapping_keys: dict[tuple[str, str], list[object]] = {}
        purity = Purity(spec.tree)
        for node in spec.tree.body:
            if isinstance(node, ast.ClassDef):
                methods = [m for m in spec.methods.values() if m.cls == node.name]
                shape, from_param = _class_shape(node, methods, purity)
                self._link(node.name, shape, from_param)
                self.shapes[node.name] = shape
                self._collect_keys(node)

    def _link(self, cls: str, shape: ClassShape, from_param: dict[str, int]) -> None:
        for attr, position in from_param.items():
            for names in self.facts.constructor_args.get(cls, []):
                name = names[position] if position < len(names) else None
                if name is not None and name in self.facts.instance_class:
                    shape.links[attr] = self.facts.instance_class[name]
                    break
            else:
                shape.scalars.add(attr)

    def _collect_keys(self, cls: ast.ClassDef) -> None:
        """Keys of `self.m[...]` writes: constants the demonstrations pass for the parameter used as the key."""
        for method in (n for n in cls.body if isinstance(n, ast.FunctionDef)):
            for node in ast.walk(method):
                targets = node.targets if isinstance(node, ast.Assign) else []
                for target in targets:
                    if not isinstance(target, ast.Subscript):
                        continue
                    attr = _self_attribute(target.value)
                    if attr is not None and isinstance(target.slice, ast.Name):
                        keys = self.mapping_keys.setdefault((cls.name, attr), [])
                        for value in self.facts.constants.get(target.slice.id, []):
                            if value not in keys and len(keys) < MAX_KEYS:
                                keys.append(value)

    def paths(self, cls: str) -> Iterable[tuple[str, str]]:
        """(expression, class) for `self` and every linked object up to MAX_DEPTH attributes away."""
        frontier = [("self", cls)]
        seen = {cls}
        for _ in range(MAX_DEPTH + 1):
            next_frontier = []
            for path, name in frontier:
                yield path, name
                for attr, target in self.shapes.get(name, ClassShape()).links.items():
                    if target not in seen:
                        seen.add(target)
                        next_frontier.append((f"{path}.{attr}", target))
            frontier = next_frontier


def _query_arguments(query_params: Sequence[str], action_params: Sequence[str], facts: DemoFacts) -> list[str]:
    """Argument lists for a pure query: action parameters, or the few constants seen for that parameter."""
    options: list[list[str]] = []
    for name in query_params:
        constants = facts.constants.get(name, [])
        few = 0 < len(constants) <= MAX_CONSTANTS_PER_PARAM
        options.append([repr(c) for c in constants] if few else list(action_params))
    return [", ".join(args) for args in itertools.islice(itertools.product(*options), MAX_QUERY_CALLS)]


def _with_negation(expression: str) -> tuple[str, str]:
    return expression, f"not {expression}"


def _argument_words(info: ActionInfo) -> dict[str, list[str]]:
    """Leading words of string arguments seen for each parameter ('sinkbasin 1' -> 'sinkbasin')."""
    words: dict[str, list[str]] = {}
    for position, param in enumerate(info.params):
        seen: list[str] = []
        for args in info.arg_values:
            value = args[position] if position < len(args) else None
            if isinstance(value, str) and " " in value:
                word = value.split()[0]
                if word not in seen:
                    seen.append(word)
        if 0 < len(seen) <= MAX_CONSTANTS_PER_PARAM // 2:
            words[param] = seen
    return words


def _atom_stream(model: StateModel, info: ActionInfo, cls: str) -> Iterator[str]:
    """Every atom in the enumerator's order, built one at a time (a caller that stops early builds no more)."""
    params = list(info.params)
    for path, name in model.paths(cls):
        shape = model.shapes.get(name, ClassShape())
        for attr in sorted(shape.scalars):
            ref = f"{path}.{attr}"
            yield from (*_with_negation(ref), f"{ref} is None", f"{ref} is not None")
            yield from (f"{ref} {op} {p}" for op in ("==", "!=") for p in params)
        for attr in sorted(shape.mappings):
            ref = f"{path}.{attr}"
            for key in model.mapping_keys.get((name, attr), []):
                yield from _with_negation(f"{ref}[{key!r}]")
            for p in params:
                yield from (*_with_negation(f"{ref}[{p}]"), f"{p} in {ref}", f"{p} not in {ref}")
        for attr in sorted(shape.collections):
            ref = f"{path}.{attr}"
            yield from _with_negation(ref)
            yield from (f"{p} {op} {ref}" for op in ("in", "not in") for p in params)
        for query, query_params in sorted(shape.queries.items()):
            for args in _query_arguments(query_params, params, model.facts):
                yield from _with_negation(f"{path}.{query}({args})")
    for param, words in _argument_words(info).items():
        yield from (f"{word!r} in {param}" for word in words)
    if cls == model.tool_class:  # a tool-calling agent's spec (precond.convert.openai): engine.tool_conditions
        yield from tool_atoms(model.tool_facts, info.name.rsplit(".", 1)[-1], params)
        yield from relations(model.tool_facts, info.name.rsplit(".", 1)[-1], params)


@dataclass(frozen=True)
class Enumerated:
    atoms: list[str]
    cut: bool
    """The stream had more than `limit` distinct atoms: those past it were never built."""


def enumerate_atoms(model: StateModel, info: ActionInfo, cls: str, limit: int | None = None) -> Enumerated:
    """The action's distinct atoms, at most `limit` of them (`engine.work.WorkBudget.enumerated`)."""
    seen: dict[str, None] = {}
    for atom in _atom_stream(model, info, cls):
        if atom not in seen:
            if limit is not None and len(seen) >= limit:
                return Enumerated(list(seen), True)
            seen[atom] = None
    return Enumerated(list(seen), False)
