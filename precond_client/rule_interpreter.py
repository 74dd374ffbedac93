"""Rules evaluated without running them: the embedded guard's restricted interpreter.

A rule is a Python expression over `self` (the agent's state) and the action's parameters. The service runs it
in its sandbox; the embedded guard (`precond_client.guard`) cannot, and never runs caller text: it parses the
rule with `ast` and builds a tree of small closures for exactly the forms the learner writes (the conditions of
`precond/engine/candidates/enumeration.py` and `tool_conditions.py`, and the and/or/not of them that ranking makes).
Each
closure applies Python's own operator to the values the state holds, the very operation the rule names, so a rule
answers and raises (`KeyError: 'cabin'`, `TypeError: ...`) as it does in the sandbox. A form outside the grammar
is refused when the rule is compiled (`OutsideGrammar`, with the node and why), never at a call.

The grammar, one entry of `FORMS` per node type: constants (None, booleans, numbers, strings); the names `self`
and the parameters; attributes the state's `Shape` declares; subscripts (a table of the state, or a value);
comparisons (`is`/`is not` only against None, True or False, whose identity is the language's); `and`, `or`,
`not`, unary minus and plus; `+`, `-`, `*`; calls of the functions in `FUNCTIONS` (`sum` of one argument: a start would
concatenate lists); tuples; list, set and generator
comprehensions with one `for` over a value (`{(f['flight_number'], f['date']) for f in flights}`,
`all(f['date'] >= '2024-05-15' for f in ...)`). A new form of the learner is one entry.

Comprehensions keep Python 3's scoping: each run of one has its own variable (a `Cell`), which what it makes
reads, later too (a generator made in a list comprehension sees the variable's last value, as a closure does); a
generator evaluates its iterable when it is made, the rest as it is consumed; nothing leaks into the next rule.

Work is bounded, since the history a rule reads grows with the conversation, a tool's result is whatever the tool
(or whoever feeds it) returned, and a set is the tenant's own text. When a rule is compiled: at most MAX_DEPTH
expressions nested, MAX_NESTING comprehensions (one in another's iterable counts as inside it), integer constants
of at most MAX_INT_BITS bits (`OutsideGrammar` otherwise). At a call, the call's rules together take at most
`Frame.budget` steps, each charged before the work it pays for (`rule_work` says what costs what). A call whose
rules run past it is refused, never allowed (`WorkExceeded` is raised like any error of a rule, and the guard
refuses a call whose rule raised). `constant_work` evaluates the parts of a rule that read nothing of the state
when a set is stored, so that a rule that runs past the budget at every call is refused there.

A table (`Shape.kind == "table"`) is a `defaultdict(dict)` in the spec (`defaultdict(list)` where `Shape.lists`):
reading a key it lacks inserts an empty dictionary (list), which a later rule of the same call sees (`key in
table`). Here the table is never changed: what a call's rules would have inserted is kept in that call's `Frame`
only, as the sandbox's copy of the state keeps it for one call.
"""

from __future__ import annotations

import ast
import operator
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from precond_client.parsing import parse_expression
from precond_client.rule_work import (
    CONTAINER_TYPES,
    MAX_INT_BITS,
    MAX_STEPS,
    Cell,
    Frame,
    SetBuilder,
    WorkExceeded,
    added,
    alike_of,
    arithmetic_cost,
    call_cost,
    charge_key,
    charged,
    compared,
    comparison_cost,
    too_large,
    weigh,
    weighed,
)

__all__ = ["FORMS", "FUNCTIONS", "LISTS", "MAX_DEPTH", "MAX_INT_BITS", "MAX_NESTING", "MAX_STEPS", "TABLE", "VALUE",
           "Frame", "OutsideGrammar", "Scope", "Shape", "WorkExceeded", "compile_rule", "constant_work"]

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


MAX_NESTING = 3
"""Comprehensions inside comprehensions, one in another's iterable included: the learner writes one
(`all(x['date'] >= ... for x in ...)`); each level in an element multiplies the work by what it iterates."""
MAX_DEPTH = 100
"""Expressions (AST nodes) inside expressions: a node is evaluated by calling its operands', so this bounds the
stack a rule takes in the agent's process; the learner's rules nest about ten."""
Evaluate = Callable[[Frame], Any]
Compiled = tuple[Shape, Evaluate]


@dataclass(frozen=True)
class Scope:
    """The names a rule may use: `self` and the action's parameters, in the order a call passes them."""

    self_shape: Shape
    params: tuple[str, ...]
    bound: tuple[str, ...] = ()
    """Variables of the comprehensions around the node (`x` in `all(x['date'] >= ... for x in flights)`), the
    innermost last."""
    nesting: int = 0
    """Comprehensions around the node (an iterable is inside its comprehension)."""
    max_nesting: int = MAX_NESTING


FUNCTIONS: dict[str, Callable[..., Any]] = {"len": len, "all": all, "any": any, "max": max, "min": min, "sum": sum}
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
        tree = parse_expression(text)
    except SyntaxError as exc:
        raise OutsideGrammar(f"not an expression: {exc.msg}") from None
    except (RecursionError, MemoryError, ValueError) as exc:
        raise OutsideGrammar(f"cannot be read: {type(exc).__name__}") from None
    return _compile_rule(tree.body, scope)


def _compile_rule(node: ast.expr, scope: Scope) -> Evaluate:
    """`compile_rule` of a parsed expression: its own evaluation charged the expressions it holds."""
    if _depth(node) > MAX_DEPTH:
        raise OutsideGrammar(f"{_text(node)}: more than {MAX_DEPTH} expressions nested")
    try:
        shape, evaluate = _compile(node, scope)
    except (RecursionError, MemoryError, ValueError) as exc:
        if isinstance(exc, OutsideGrammar):
            raise
        raise OutsideGrammar(f"cannot be read: {type(exc).__name__}") from None
    if shape.kind != "value":
        raise OutsideGrammar(f"{_text(node)} is the state's {shape.kind}, not a value")
    steps = _nodes([node])

    def rule(frame: Frame) -> Any:
        frame.charge(steps)
        return evaluate(frame)

    return rule


def _depth(node: ast.AST) -> int:
    deepest, stack = 0, [(node, 1)]
    while stack:
        current, depth = stack.pop()
        deepest = max(deepest, depth)
        if depth <= MAX_DEPTH:
            stack.extend((child, depth + 1) for child in ast.iter_child_nodes(current))
    return deepest


def _nodes(nodes: Iterable[ast.AST]) -> int:
    """The expressions a node evaluates (each a step, whatever it does in constant time)."""
    return sum(isinstance(n, ast.expr) for node in nodes for n in ast.walk(node))


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
    if type(value) is int and value.bit_length() > MAX_INT_BITS:
        raise OutsideGrammar(f"{_text(node)}: an integer of more than {MAX_INT_BITS:,} bits")
    return VALUE, lambda frame: value


def _name(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Name)
    if node.id in scope.bound:
        hops = scope.bound[::-1].index(node.id)  # the innermost comprehension that binds it
        if hops == 0:
            return VALUE, lambda frame: frame.env.value
        if hops == 1:
            return VALUE, lambda frame: frame.env.outer.value

        def read(frame: Frame) -> Any:
            cell = frame.env
            for _ in range(hops):
                cell = cell.outer  # type: ignore[union-attr]
            return cell.value  # type: ignore[union-attr]

        return VALUE, read
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
    if isinstance(node.value, ast.Name) and node.value.id == "self" and "self" not in scope.bound:
        return found, lambda frame: getattr(frame.state, name)  # `self.results`: the state read at once
    return found, lambda frame: getattr(owner(frame), name)


def _subscript(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Subscript)
    if isinstance(node.slice, ast.Slice):
        raise OutsideGrammar(f"{_text(node)}: a slice")
    shape, container = _compile(node.value, scope)
    key = _value(node.slice, scope)
    known = node.slice.value if isinstance(node.slice, ast.Constant) and type(node.slice.value) is str else None
    if shape.kind == "table":
        path, empty = ast.unparse(node.value), list if shape.lists else dict

        def read(frame: Frame) -> Any:
            table, wanted = container(frame), known
            if wanted is None:  # `x['key']`, the common form, reads its key without a call (a string: no charge)
                wanted = key(frame)
                if type(wanted) is not str:  # a string's hash is kept with it
                    charge_key(wanted, frame)
            try:
                return table[wanted]
            except KeyError:
                frame.remember(path, wanted)  # what the defaultdict inserts, for this call only
                return empty()

        return VALUE, read
    if shape.kind != "value":
        raise OutsideGrammar(f"{_text(node)}: the state's {shape.kind} is not subscripted")
    if known is not None:
        return VALUE, lambda frame: container(frame)[known]

    def item(frame: Frame) -> Any:
        value, wanted = container(frame), key(frame)
        if type(wanted) is not str:  # a string's hash is kept with it
            charge_key(wanted, frame)
        return value[wanted]

    return VALUE, item


def _contains(path: str, table: Evaluate, negated: bool) -> Callable[[Any, Frame], Any]:
    """`x in table` as the spec's defaultdict answers it after this call's rules read it."""

    def contains(item: Any, frame: Frame) -> bool:
        frame.charge(weigh(item, frame))
        found = item in table(frame) or frame.remembers(path, item)
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
        steps.append((evaluate, charged(COMPARE[type(op)], comparison_cost(op))))
    if len(steps) == 1:
        (right_value, test), = steps
        if right_value is None:
            return VALUE, lambda frame: test(left(frame), frame)
        return VALUE, compared(left, right_value, COMPARE[type(node.ops[0])], comparison_cost(node.ops[0]))

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

    def unary(frame: Frame) -> Any:
        value = operand(frame)
        if type(value) is int:  # negation copies it
            frame.charge(weigh(value, frame))
        return apply(value)

    return VALUE, unary


def _bin_op(node: ast.expr, scope: Scope) -> Compiled:
    """`a + b`, `a - b`, `a * b` as Python answers them, charged first (`rule_work.arithmetic_cost`)."""
    assert isinstance(node, ast.BinOp)
    apply = ARITHMETIC.get(type(node.op))
    if apply is None:
        raise OutsideGrammar(f"{_text(node)}: the operator {type(node.op).__name__}")
    left, right = _value(node.left, scope), _value(node.right, scope)
    repeats = isinstance(node.op, ast.Mult)

    def arithmetic(frame: Frame) -> Any:
        a, b = left(frame), right(frame)
        frame.charge(arithmetic_cost(a, b, repeats, frame))
        result = apply(a, b)
        if type(result) is int and result.bit_length() > MAX_INT_BITS:
            raise too_large()
        if type(result) is set and alike_of(a, frame) > 1:  # a difference holds the values of `a` that hash alike
            frame.alike[id(result)] = (result, alike_of(a, frame))
        return result

    return VALUE, arithmetic


def _call(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Call)
    function = FUNCTIONS.get(node.func.id) if isinstance(node.func, ast.Name) else None
    if function is None or node.keywords or any(isinstance(a, ast.Starred) for a in node.args):
        raise OutsideGrammar(f"{_text(node)}: calls {', '.join(FUNCTIONS)} only, with plain arguments")
    if function is sum and len(node.args) != 1:
        raise OutsideGrammar(f"{_text(node)}: sum of one argument only (a start would concatenate lists)")
    args = [_value(a, scope) for a in node.args]
    compares = function is max or function is min

    def call(frame: Frame) -> Any:
        values = [a(frame) for a in args]
        if function is sum:
            return _sum(values[0], frame)
        frame.charge(call_cost(function, values, frame))
        if compares and len(values) == 1 and type(values[0]) not in CONTAINER_TYPES and type(values[0]) is not str:
            return function(weighed(values[0], frame))  # a generator's items: charged as they come
        return function(*values)

    return VALUE, call


def _sum(values: Any, frame: Frame) -> Any:
    """`sum(values)` as Python sums them (the same items in the same order, floats included), each addition charged
    before it is made (`rule_work.added`); an integer total past MAX_INT_BITS is refused, as `a + b`'s is."""
    frame.charge(1)
    total = sum(added(values, frame))
    if type(total) is int and total.bit_length() > MAX_INT_BITS:
        raise too_large()
    return total


def _tuple(node: ast.expr, scope: Scope) -> Compiled:
    assert isinstance(node, ast.Tuple)
    parts = [_value(e, scope) for e in node.elts]
    return VALUE, lambda frame: tuple(part(frame) for part in parts)


_SKIP = object()
"""An item a comprehension's `if` leaves out."""


def _comprehension(node: ast.expr, scope: Scope) -> Compiled:
    """`[e for x in xs if c]`, `{...}`, `(... for ...)`: one `for` over a value, a plain variable, any `if`s.
    As in Python 3, `xs` is evaluated (and iterated from) when the comprehension is made, in the scope around it;
    each run has its own variable; a generator runs its body as it is consumed, so `all(...)` stops at the first
    false item, raising only where Python would. An item costs the expressions its body holds."""
    assert isinstance(node, ast.ListComp | ast.SetComp | ast.GeneratorExp)
    if len(node.generators) != 1:
        raise OutsideGrammar(f"{_text(node)}: one `for` only")
    if scope.nesting >= scope.max_nesting:
        raise OutsideGrammar(f"{_text(node)}: more than {scope.max_nesting} comprehensions nested (each multiplies "
                             "the work)")
    generator = node.generators[0]
    target = generator.target
    if not isinstance(target, ast.Name) or generator.is_async or target.id == "self":
        raise OutsideGrammar(f"{_text(node)}: the variable must be a plain name")
    around = replace(scope, nesting=scope.nesting + 1)
    iterate = _value(generator.iter, around)
    inner = replace(around, bound=(*scope.bound, target.id))
    element = _value(node.elt, inner)
    tests = [_value(test, inner) for test in generator.ifs]
    per_item = 1 + _nodes([node.elt, *generator.ifs])

    def body(frame: Frame) -> Any:
        for test in tests:
            if not test(frame):
                return _SKIP
        return element(frame)

    def run(frame: Frame, keep: Callable[[Any], None]) -> None:
        iterator = iter(iterate(frame))
        cell = Cell(frame.env)
        outer, frame.env = frame.env, cell
        try:
            for item in iterator:
                frame.charge(per_item)
                cell.value = item
                value = body(frame)
                if value is not _SKIP:
                    keep(value)
        finally:
            frame.env = outer

    if isinstance(node, ast.ListComp):
        def listed(frame: Frame) -> list[Any]:
            made: list[Any] = []
            run(frame, made.append)
            return made
        return VALUE, listed
    if isinstance(node, ast.SetComp):
        def setted(frame: Frame) -> set[Any]:
            builder = SetBuilder(frame)
            run(frame, builder.add)
            return builder.build()
        return VALUE, setted
    return VALUE, lambda frame: _lazy(frame, Cell(frame.env), iter(iterate(frame)), per_item, body)


def _lazy(frame: Frame, cell: Cell, iterator: Iterator[Any], per_item: int, body: Evaluate) -> Iterator[Any]:
    """A generator expression's items: its own variable bound, the body evaluated in its scope, whichever
    comprehension consumes it."""
    for item in iterator:
        frame.charge(per_item)
        cell.value = item
        outer, frame.env = frame.env, cell
        try:
            value = body(frame)
        finally:
            frame.env = outer
        if value is not _SKIP:
            yield value


def constant_work(text: str, frame: Frame) -> str | None:
    """Why a rule is refused when a set is stored: a part of it that reads nothing of the state or the call
    (`len([v * v for v in (0xff,)]) == 1`) takes the guard past its budget (`frame`'s, shared by the set's
    rules) at every call. Each such part is evaluated here, as the guard would, within that budget; None when
    all are within it, raise (the verdicts say so) or are outside the grammar (the guard does not embed the set)."""
    try:
        tree = parse_expression(text.strip())
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None  # the static check names it
    if _depth(tree.body) > MAX_DEPTH:
        return None
    for part in _closed(tree.body):
        try:
            evaluate = _compile_rule(part, Scope(VALUE, (), max_nesting=MAX_DEPTH))
        except OutsideGrammar:
            continue
        try:
            evaluate(frame)
        except WorkExceeded as exc:
            return f"{_text(part)} reads nothing of the state or the call, and {exc}"
        except Exception:  # a part that raises makes the rule raise at every call: a verdict, as the service's
            continue
    return None


def _closed(node: ast.expr) -> Iterator[ast.expr]:
    """The largest parts of an expression that name no variable from outside them (only constants and their own
    comprehensions' variables) and do some work (a comprehension, arithmetic, a call)."""
    if not _free(node):
        if any(isinstance(n, ast.BinOp | ast.Call | ast.ListComp | ast.SetComp | ast.GeneratorExp)
               for n in ast.walk(node)):
            yield node
        return
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.expr):
            yield from _closed(child)
        elif isinstance(child, ast.comprehension):
            for part in (child.iter, *child.ifs):
                yield from _closed(part)


def _free(node: ast.AST) -> set[str]:
    """The names an expression reads from outside it (a called builtin's name aside)."""
    if isinstance(node, ast.Name):
        return {node.id}
    if isinstance(node, ast.ListComp | ast.SetComp | ast.GeneratorExp | ast.DictComp):
        inside: set[str] = set()
        outside: set[str] = set()
        for generator in node.generators:
            outside |= _free(generator.iter)
            inside |= set().union(*(_free(test) for test in generator.ifs)) | _free(generator.target)
        body = [node.key, node.value] if isinstance(node, ast.DictComp) else [node.elt]
        inside |= set().union(*(_free(part) for part in body))
        bound = {n.id for g in node.generators for n in ast.walk(g.target) if isinstance(n, ast.Name)}
        return outside | (inside - bound)
    names: set[str] = set()
    for child in ast.iter_child_nodes(node):
        if isinstance(node, ast.Call) and child is node.func and isinstance(child, ast.Name) and child.id in FUNCTIONS:
            continue
        names |= _free(child)
    return names


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
