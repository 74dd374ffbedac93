"""Rules evaluated without running them: the embedded guard's restricted interpreter.

A rule is a Python expression over `self` (the agent's state) and the action's parameters. The service runs it
in its sandbox; the embedded guard (`precond_client.guard`) cannot, and never runs caller text: it parses the
rule with `ast` and builds a tree of small closures for exactly the forms the learner writes (the conditions of
`precond/engine/enumeration.py` and `tool_conditions.py`, and the and/or/not of them that ranking makes). Each
closure applies Python's own operator to the values the state holds, the very operation the rule names, so a rule
answers and raises (`KeyError: 'cabin'`, `TypeError: ...`) as it does in the sandbox. A form outside the grammar
is refused when the rule is compiled (`OutsideGrammar`, with the node and why), never at a call.

The grammar, one entry of `FORMS` per node type: constants (None, booleans, numbers, strings); the names `self`
and the parameters; attributes the state's `Shape` declares; subscripts (a table of the state, or a value);
comparisons (`is`/`is not` only against None, True or False, whose identity is the language's); `and`, `or`,
`not`, unary minus and plus; `+`, `-`, `*`; calls of the functions in `FUNCTIONS`; tuples; list, set and generator
comprehensions with one `for` over a value (`{(f['flight_number'], f['date']) for f in flights}`,
`all(f['date'] >= '2024-05-15' for f in ...)`). A new form of the learner is one entry.

Work is bounded twice, since the history a rule reads grows with the conversation and a set is the tenant's own
text: a rule nests at most MAX_NESTING comprehensions (more is refused when the set is loaded, `OutsideGrammar`),
and one call's rules together take at most `Frame.budget` steps (an item of a comprehension is one; a comparison
or `in` with a collection costs its size). A call whose rules run past it is refused, never allowed
(`WorkExceeded` is raised like any error of a rule, and the guard refuses a call whose rule raised).

A table (`Shape.kind == "table"`) is a `defaultdict(dict)` in the spec (`defaultdict(list)` where `Shape.lists`):
reading a key it lacks inserts an empty dictionary (list), which a later rule of the same call sees (`key in
table`). Here the table is never changed: what a call's rules would have inserted is kept in that call's `Frame`
only, as the sandbox's copy of the state keeps it for one call.
"""

from __future__ import annotations

import ast
import operator
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

Kind = Literal["value", "table", "object"]


@dataclass(frozen=True)
class Shape:
    """What an expression is, known before anything runs: a plain value, a table, or an object whose attributes
    (and only those) a rule may read."""

    kind: Kind
    attributes: Mapping[str, Shape] = field(default_factory=dict)
    lists: bool = False
    """A table whose missing key reads as an empty list (`defaultdict(list)`), not an empty dictionary."""


VALUE = Shape("value")
TABLE = Shape("table")
LISTS = Shape("table", lists=True)


class OutsideGrammar(ValueError):
    """A rule the interpreter does not evaluate: the message names the part and the reason."""


MAX_NESTING = 2
"""Comprehensions inside comprehensions: the learner writes one (`all(x['date'] >= ... for x in ...)`); each
level multiplies the work by the length of what it iterates."""
MAX_STEPS = 200_000
"""Steps one call's rules may take: a rule linear in a long conversation's results uses a few thousand."""
COLLECTIONS = (list, tuple, set, frozenset, dict)
SIZED = (*COLLECTIONS, str)


class WorkExceeded(RuntimeError):
    """A call's rules ran past their step budget: the call is refused, with this as the reason."""


class Frame:
    """One call's evaluation: the state, the arguments by position, the keys its rules inserted into tables, and
    the steps left of its budget."""

    __slots__ = ("args", "bound", "budget", "inserted", "state")

    def __init__(self, state: object, args: Sequence[Any], budget: int = MAX_STEPS) -> None:
        self.state = state
        self.args = args
        self.inserted: set[tuple[str, Any]] | None = None
        self.bound: dict[str, Any] = {}
        """The comprehensions' variables, while one runs."""
        self.budget = budget

    def charge(self, steps: int) -> None:
        self.budget -= steps
        if self.budget < 0:
            raise WorkExceeded(f"the rules took more than their budget of steps ({MAX_STEPS:,} a call): "
                               "refused, not judged")


Evaluate = Callable[[Frame], Any]
Compiled = tuple[Shape, Evaluate]


@dataclass(frozen=True)
class Scope:
    """The names a rule may use: `self` and the action's parameters, in the order a call passes them."""

    self_shape: Shape
    params: tuple[str, ...]
    bound: tuple[str, ...] = ()
    """Variables of the comprehensions around the node (`x` in `all(x['date'] >= ... for x in flights)`)."""
    nesting: int = 0
    """Comprehensions around the node."""


FUNCTIONS: dict[str, Callable[..., Any]] = {"len": len, "all": all, "any": any, "max": max, "min": min}
"""Builtins a rule may call; each gets values only."""
ARITHMETIC: dict[type[ast.operator], Callable[[Any, Any], Any]] = {
    ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
}
"""The arithmetic a policy states (`max(0, total_baggages - 2 * len(passengers))`)."""
COMPARE: dict[type[ast.cmpop], Callable[[Any, Any], Any]] = {
    ast.Eq: operator.eq, ast.NotEq: operator.ne, ast.Lt: operator.lt, ast.LtE: operator.le, ast.Gt: operator.gt,
    ast.GtE: operator.ge, ast.In: lambda a, b: a in b, ast.NotIn: lambda a, b: a not in b,
    ast.Is: operator.is_, ast.IsNot: operator.is_not,
}
SINGLETONS = (None, True, False)
UNARY: dict[type[ast.unaryop], Callable[[Any], Any]] = {
    ast.Not: operator.not_, ast.USub: operator.neg, ast.UAdd: operator.pos,
}


def compile_rule(text: str, scope: Scope) -> Evaluate:
    """The rule as a function of a `Frame` whose truth is the rule's verdict; `OutsideGrammar` when it is not one
    of the forms above (or does not parse)."""
    try:
        tree = ast.parse(text, mode="eval")
        shape, evaluate = _compile(tree.body, scope)
    except OutsideGrammar:
        raise
    except SyntaxError as exc:
        raise OutsideGrammar(f"not an expression: {exc.msg}") from None
    except (RecursionError, MemoryError, ValueError) as exc:
        raise OutsideGrammar(f"cannot be read: {type(exc).__name__}") from None
    if shape.kind != "value":
        raise OutsideGrammar(f"{_text(tree.body)} is the state's {shape.kind}, not a value")
    return evaluate


def _compile(node: ast.expr, scope: Scope) -> Compiled:
    form = FORMS.get(type(node))
    if form is None:
        raise OutsideGrammar(f"{_text(node)}: {type(node).__name__} is not among the forms the learner writes")
    return form(node, scope)


def _value(node: ast.expr, scope: Scope) -> Evaluate:
    shape, evaluate = _compile(node, scope)
    if shape.kind != "value":
        raise OutsideGrammar(f"{_text(node)}: the state's {shape.kind} is read only by attribute or subscript"
                             + (" (or `in`)" if shape.kind == "table" else ""))
    return evaluate


def _text(node: ast.AST) -> str:
    text = ast.unparse(node)
    return f"`{text if len(text) <= 80 else text[:77] + '...'}`"


def _constant(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Constant)
    value = node.value
    if not (value is None or isinstance(value, bool | int | float | str)):
        raise OutsideGrammar(f"{_text(node)}: a {type(value).__name__} constant")
    return VALUE, lambda frame: value


def _name(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Name)
    if node.id in scope.bound:
        name = node.id
        return VALUE, lambda frame: frame.bound[name]
    if node.id == "self":
        return scope.self_shape, lambda frame: frame.state
    if node.id in scope.params:
        position = scope.params.index(node.id)
        return VALUE, lambda frame: frame.args[position]
    raise OutsideGrammar(f"`{node.id}` is neither `self` nor a parameter ({', '.join(scope.params) or 'none'})")


def _attribute(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Attribute)
    shape, owner = _compile(node.value, scope)
    found = shape.attributes.get(node.attr) if shape.kind == "object" else None
    if found is None:
        raise OutsideGrammar(f"{_text(node)}: {node.attr!r} is not an attribute of the state")
    name = node.attr
    return found, lambda frame: getattr(owner(frame), name)


def _subscript(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Subscript)
    if isinstance(node.slice, ast.Slice):
        raise OutsideGrammar(f"{_text(node)}: a slice")
    shape, container = _compile(node.value, scope)
    key = _value(node.slice, scope)
    if shape.kind == "table":
        path, empty = ast.unparse(node.value), list if shape.lists else dict

        def read(frame: Frame) -> Any:
            table, wanted = container(frame), key(frame)
            try:
                return table[wanted]
            except KeyError:
                if frame.inserted is None:
                    frame.inserted = set()
                frame.inserted.add((path, wanted))  # what the defaultdict inserts, for this call only
                return empty()

        return VALUE, read
    if shape.kind != "value":
        raise OutsideGrammar(f"{_text(node)}: the state's {shape.kind} is not subscripted")
    return VALUE, lambda frame: container(frame)[key(frame)]


def _charged(test: Callable[[Any, Any], Any]) -> Callable[[Any, Any, Frame], Any]:
    """The comparison, its cost charged first: a collection's size (`==` and `in` walk it), else one step."""

    def compare(left: Any, right: Any, frame: Frame) -> Any:
        frame.charge(1 + (len(left) if isinstance(left, COLLECTIONS) else 0)
                     + (len(right) if isinstance(right, COLLECTIONS) else 0))
        return test(left, right)

    return compare


def _contains(path: str, table: Evaluate, negated: bool) -> Callable[[Any, Frame], Any]:
    """`x in table` as the spec's defaultdict answers it after this call's rules read it."""

    def contains(item: Any, frame: Frame) -> bool:
        found = item in table(frame) or (frame.inserted is not None and (path, item) in frame.inserted)
        return not found if negated else found

    return contains


def _compare(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Compare)
    left = _value(node.left, scope)
    steps: list[tuple[Evaluate | None, Callable[..., Any]]] = []
    for number, (op, right) in enumerate(zip(node.ops, node.comparators, strict=True)):
        shape, evaluate = _compile(right, scope)
        last = number == len(node.ops) - 1
        if shape.kind == "table" and isinstance(op, ast.In | ast.NotIn) and last:
            steps.append((None, _contains(ast.unparse(right), evaluate, isinstance(op, ast.NotIn))))
            continue
        if shape.kind != "value":
            raise OutsideGrammar(f"{_text(right)}: the state's {shape.kind} is not compared")
        if isinstance(op, ast.Is | ast.IsNot) and not (isinstance(right, ast.Constant) and any(
                right.value is s for s in SINGLETONS)):
            raise OutsideGrammar(f"{_text(node)}: `is` compares with None, True or False only")
        steps.append((evaluate, _charged(COMPARE[type(op)])))
    if len(steps) == 1:
        (right_value, test), = steps
        if right_value is None:
            return VALUE, lambda frame: test(left(frame), frame)
        return VALUE, lambda frame: test(left(frame), right_value(frame), frame)

    def chained(frame: Frame) -> Any:
        current, result = left(frame), True
        for right_value, test in steps:
            if right_value is None:  # a table: the last operand
                result = test(current, frame)
            else:
                following = right_value(frame)
                result, current = test(current, following, frame), following
            if not result:
                return result
        return result

    return VALUE, chained


def _bool_op(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.BoolOp)
    parts = [_value(value, scope) for value in node.values]
    if isinstance(node.op, ast.And):
        def all_of(frame: Frame) -> Any:
            value = True
            for part in parts:
                value = part(frame)
                if not value:
                    return value
            return value
        return VALUE, all_of

    def any_of(frame: Frame) -> Any:
        value = False
        for part in parts:
            value = part(frame)
            if value:
                return value
        return value
    return VALUE, any_of


def _unary(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.UnaryOp)
    apply = UNARY.get(type(node.op))
    if apply is None:
        raise OutsideGrammar(f"{_text(node)}: the operator {type(node.op).__name__}")
    operand = _value(node.operand, scope)
    return VALUE, lambda frame: apply(operand(frame))


def _size(value: Any) -> int:
    return len(value) if isinstance(value, SIZED) else 0


def _bin_op(node: ast.expr, scope: Scope) -> Compiled:
    """`a + b`, `a - b`, `a * b` as Python answers them; what a sequence would become (`[0] * n`, `s + s`) is
    charged before it is built."""
    assert isinstance(node, ast.BinOp)
    apply = ARITHMETIC.get(type(node.op))
    if apply is None:
        raise OutsideGrammar(f"{_text(node)}: the operator {type(node.op).__name__}")
    left, right = _value(node.left, scope), _value(node.right, scope)
    repeats = isinstance(node.op, ast.Mult)

    def arithmetic(frame: Frame) -> Any:
        a, b = left(frame), right(frame)
        built = _size(a) + _size(b)
        if repeats and built:
            times = b if _size(a) else a
            built = built * times if isinstance(times, int) and not isinstance(times, bool) and times > 0 else built
        frame.charge(1 + built)
        return apply(a, b)

    return VALUE, arithmetic


def _call(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Call)
    function = FUNCTIONS.get(node.func.id) if isinstance(node.func, ast.Name) else None
    if function is None or node.keywords or any(isinstance(a, ast.Starred) for a in node.args):
        raise OutsideGrammar(f"{_text(node)}: calls {', '.join(FUNCTIONS)} only, with plain arguments")
    args = [_value(a, scope) for a in node.args]

    def call(frame: Frame) -> Any:
        values = [a(frame) for a in args]
        frame.charge(1 + (sum(_size(v) for v in values) if function is not len else 0))  # max, min walk them
        return function(*values)

    return VALUE, call


def _tuple(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Tuple)
    parts = [_value(e, scope) for e in node.elts]
    return VALUE, lambda frame: tuple(part(frame) for part in parts)


def _comprehension(node: ast.expr, scope: Scope) -> Compiled:
    """`[e for x in xs if c]`, `{...}`, `(... for ...)`: one `for` over a value, a plain variable, any `if`s.
    A generator is lazy, as Python's is: `all(...)` stops at the first false item, raising only where it would."""
    assert isinstance(node, ast.ListComp | ast.SetComp | ast.GeneratorExp)
    if len(node.generators) != 1:
        raise OutsideGrammar(f"{_text(node)}: one `for` only")
    if scope.nesting >= MAX_NESTING:
        raise OutsideGrammar(f"{_text(node)}: more than {MAX_NESTING} comprehensions nested (each multiplies the work)")
    generator = node.generators[0]
    target = generator.target
    if not isinstance(target, ast.Name) or generator.is_async or target.id == "self":
        raise OutsideGrammar(f"{_text(node)}: the variable must be a plain name")
    iterate = _value(generator.iter, scope)
    inner = Scope(scope.self_shape, scope.params, (*scope.bound, target.id), scope.nesting + 1)
    element = _value(node.elt, inner)
    tests = [_value(test, inner) for test in generator.ifs]
    name = target.id

    def items(frame: Frame) -> Any:
        before = frame.bound.get(name, _UNBOUND)
        try:
            for item in iterate(frame):
                frame.charge(1)
                frame.bound[name] = item
                if all(test(frame) for test in tests):
                    yield element(frame)
        finally:
            if before is _UNBOUND:
                frame.bound.pop(name, None)
            else:
                frame.bound[name] = before

    if isinstance(node, ast.ListComp):
        return VALUE, lambda frame: list(items(frame))
    if isinstance(node, ast.SetComp):
        return VALUE, lambda frame: set(items(frame))
    return VALUE, items


_UNBOUND = object()


FORMS: dict[type[ast.expr], Callable[[ast.expr, Scope], Compiled]] = {
    ast.Tuple: _tuple,
    ast.ListComp: _comprehension,
    ast.SetComp: _comprehension,
    ast.GeneratorExp: _comprehension,
    ast.Constant: _constant,
    ast.Name: _name,
    ast.Attribute: _attribute,
    ast.Subscript: _subscript,
    ast.Compare: _compare,
    ast.BoolOp: _bool_op,
    ast.UnaryOp: _unary,
    ast.Call: _call,
    ast.BinOp: _bin_op,
}
