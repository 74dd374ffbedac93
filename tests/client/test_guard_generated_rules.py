"""Generated rules and states, judged by the embedded guard's interpreter and by Python as the service's sandbox
runs a rule (`lambda self, <params>: (<rule>)`, built as an AST, over a state whose tables are `defaultdict`s):
each must give the same verdict (the rule's truth), or raise the same exception with the same message; where the
guard refuses for its bounds (`WorkExceeded`), Python must refuse too (raise, or run past the service's 2 s of
CPU a call in a child of its own). A rule outside the guard's grammar makes a set the guard does not embed: no
verdict to compare, but one that `constant_work` refuses when a set is stored is counted apart.

The rules are made of the grammar's forms (constants, the parameters, the state's tables and values, subscripts,
comparisons and their chains, and/or/not, arithmetic, `len`/`all`/`any`/`max`/`min`/`sum`, tuples, list, set and
generator comprehensions whose variables shadow each other and the parameters); the states of JSON values
(integers that hash alike among them) and tuples for a call's arrays, as the guard reads them. The corpus holds
the attacks' rules (`test_guard_attacks`). `--guard-cases N` runs N generated cases (the suite: 150; the
10,000 of the guard's differential figure: `python -m pytest tests/client/test_guard_generated_rules.py
--guard-cases 10000 -s`, which prints the count of each outcome).
"""

from __future__ import annotations

import ast
import builtins
import copy
import multiprocessing
import resource
import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from precond_client.rule_interpreter import (
    LISTS,
    TABLE,
    VALUE,
    Frame,
    OutsideGrammar,
    Scope,
    Shape,
    WorkExceeded,
    compile_rule,
    constant_work,
)
from tests.client.test_guard_attacks import squarings

PARAMS = ("a", "b", "c")
SHAPE = Shape("object", {"results": TABLE, "seen": LISTS, "last_ok": VALUE})
P = 2**61 - 1
SERVICE_CPU_S = 2
"""The sandbox's CPU time for one proposed call (`Limits.unit_cpu_s`): past it, the service refuses the call."""
TARGETS = ("x", "y", "a")
"""Comprehension variables: `a` shadows a parameter, and the others shadow each other when nested."""


class State:
    """The spec's state as the sandbox holds it (`defaultdict`s), or as the guard reads it (plain dictionaries)."""

    def __init__(self, results: dict[str, Any], seen: dict[str, list[Any]], last_ok: Any, python: bool) -> None:
        self.results: dict[str, Any] = defaultdict(dict, copy.deepcopy(results)) if python else results
        self.seen: dict[str, Any] = defaultdict(list, copy.deepcopy(seen)) if python else seen
        self.last_ok = last_ok


Outcome = tuple[Any, ...]
"""("value", truth), ("raised", type, message), ("bounded",) for the guard's refusal, ("refused",) for the
service's."""


@dataclass(frozen=True)
class Case:
    rule: str
    results: dict[str, Any]
    seen: dict[str, list[Any]]
    last_ok: Any
    args: tuple[Any, ...]


def _tupled(value: Any) -> Any:
    return tuple(_tupled(v) for v in value) if isinstance(value, list) else value


SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-3, 3), st.sampled_from([7, 7 + P, 7 + 2 * P, -1, -2,
                                                                                    2**70, 2.5, 0.0]),
                    st.text("ab-", max_size=3))
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.sampled_from(["date", "n", "a"]), inner, max_size=3), max_leaves=10)
KEYS = st.sampled_from(["t", "u", "k1", 7, 7 + P])


@st.composite
def expressions(draw: st.DrawFn, depth: int = 3, bound: tuple[str, ...] = ()) -> ast.expr:
    """An expression of the guard's grammar whose names are the parameters and the comprehensions' variables."""
    if depth <= 0 or draw(st.integers(0, 4)) == 0:
        return draw(_leaf(bound))
    form = draw(st.sampled_from(["compare", "bool", "unary", "arith", "call", "tuple", "comp", "subscript",
                                 "table_in"]))
    sub = expressions(depth - 1, bound)
    if form == "compare":
        ops = draw(st.lists(st.sampled_from([ast.Eq(), ast.NotEq(), ast.Lt(), ast.LtE(), ast.Gt(), ast.GtE(),
                                             ast.In(), ast.NotIn()]), min_size=1, max_size=2))
        return ast.Compare(draw(sub), ops, [draw(sub) for _ in ops])
    if form == "bool":
        return ast.BoolOp(draw(st.sampled_from([ast.And(), ast.Or()])), draw(st.lists(sub, min_size=2, max_size=3)))
    if form == "unary":
        return ast.UnaryOp(draw(st.sampled_from([ast.Not(), ast.USub(), ast.UAdd()])), draw(sub))
    if form == "arith":
        return ast.BinOp(draw(sub), draw(st.sampled_from([ast.Add(), ast.Sub(), ast.Mult()])), draw(sub))
    if form == "call":
        name = draw(st.sampled_from(["len", "all", "any", "max", "min", "sum"]))
        count = draw(st.integers(1, 2)) if name in ("max", "min") else 1
        return ast.Call(ast.Name(name), [draw(sub) for _ in range(count)], [])
    if form == "tuple":
        return ast.Tuple(draw(st.lists(sub, max_size=3)))
    if form == "subscript":
        return ast.Subscript(draw(sub), draw(_leaf(bound)))
    if form == "table_in":
        return ast.Compare(draw(sub), [draw(st.sampled_from([ast.In(), ast.NotIn()]))], [_attribute("results")])
    target = draw(st.sampled_from(TARGETS))
    inner = (*bound, target)
    kind = draw(st.sampled_from([ast.ListComp, ast.SetComp, ast.GeneratorExp]))
    ifs = draw(st.lists(expressions(depth - 1, inner), max_size=1))
    loop = ast.comprehension(ast.Name(target), draw(sub), ifs, 0)
    return kind(draw(expressions(depth - 1, inner)), [loop])


def _attribute(name: str) -> ast.expr:
    return ast.Attribute(ast.Name("self"), name)


@st.composite
def _leaf(draw: st.DrawFn, bound: tuple[str, ...]) -> ast.expr:
    names = [*PARAMS, *bound]
    choice = draw(st.integers(0, 5))
    if choice == 0:
        value: Any = draw(SCALARS)
        return ast.Constant(value)
    if choice == 1:
        return _attribute("last_ok")
    if choice == 2:
        table = _attribute(draw(st.sampled_from(["results", "seen"])))
        key: Any = draw(KEYS)
        return ast.Subscript(table, ast.Constant(key))
    if choice == 3:
        tool = ast.Subscript(_attribute("results"), ast.Constant(draw(st.sampled_from(["t", "u"]))))
        return ast.Subscript(tool, ast.Name(draw(st.sampled_from(names))))
    return ast.Name(draw(st.sampled_from(names)))


@st.composite
def cases(draw: st.DrawFn) -> Case:
    rule = ast.unparse(ast.fix_missing_locations(ast.Expression(draw(expressions()))))
    results = {tool: draw(st.dictionaries(KEYS, VALUES, max_size=3)) for tool in ("t", "u")}
    seen = {"t": draw(st.lists(VALUES, max_size=4))}
    args = tuple(_tupled(draw(VALUES)) for _ in PARAMS)
    return Case(rule, results, seen, draw(SCALARS), args)


def guard_outcome(case: Case) -> Outcome | None:
    """("value", truth) or ("raised", type, message) or ("bounded",) for `WorkExceeded`; None when the rule is
    outside the grammar."""
    try:
        evaluate = compile_rule(case.rule, Scope(SHAPE, PARAMS))
    except OutsideGrammar:
        return None
    try:
        return ("value", bool(evaluate(Frame(State(case.results, case.seen, case.last_ok, False), case.args))))
    except WorkExceeded:
        return ("bounded",)
    except Exception as exc:
        return ("raised", type(exc).__name__, str(exc))


def python_outcome(case: Case) -> Outcome:
    """The rule as the sandbox compiles it: a function of `self` and the parameters, built as an AST."""
    body = ast.parse(case.rule, mode="eval").body
    arguments = ast.arguments(posonlyargs=[], args=[ast.arg("self"), *(ast.arg(p) for p in PARAMS)], vararg=None,
                              kwonlyargs=[], kw_defaults=[], kwarg=None, defaults=[])
    with warnings.catch_warnings():  # `(1, 2)[0]`-like constants: Python's compile warns, as in the sandbox
        warnings.simplefilter("ignore", SyntaxWarning)
        code = compile(ast.fix_missing_locations(ast.Expression(ast.Lambda(arguments, body))), "<pre>", "eval")
    names = {name: getattr(builtins, name) for name in ("len", "all", "any", "max", "min", "sum")}
    function = eval(code, {"__builtins__": names})  # the generated rule, never caller text
    try:
        return ("value", bool(function(State(case.results, case.seen, case.last_ok, True), *case.args)))
    except Exception as exc:
        return ("raised", type(exc).__name__, str(exc))


def _bounded_child(case: Case, answers: Any) -> None:
    resource.setrlimit(resource.RLIMIT_CPU, (SERVICE_CPU_S, SERVICE_CPU_S))
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
    answers.put(python_outcome(case))


def service_outcome(case: Case) -> Outcome:
    """Python in a child of its own under the service's CPU time a call: ("refused",) when it runs past it."""
    context = multiprocessing.get_context("fork")
    answers = context.Queue()
    child = context.Process(target=_bounded_child, args=(case, answers))
    child.start()
    child.join(SERVICE_CPU_S * 10)
    if child.is_alive():
        child.kill()
        child.join()
    return answers.get() if child.exitcode == 0 else ("refused",)


def judge(case: Case) -> tuple[str, str | None]:
    """The outcome's kind, and a disagreement (or None)."""
    guard = guard_outcome(case)
    if guard is None:
        refused = constant_work(case.rule, Frame(None, ()))
        return ("refused when stored" if refused else "not embeddable"), None
    if guard == ("bounded",):
        python = service_outcome(case)
        agreed = python[0] in ("raised", "refused")
        return "refused by both", None if agreed else f"{case}: the guard refused for its bounds, Python {python}"
    python = python_outcome(case)
    kind = "raised" if guard[0] == "raised" else "judged"
    return kind, None if guard == python else f"{case}: the guard {guard}, Python {python}"


def _flights(numbers: list[Any], first: str = "2024-05-20") -> list[dict[str, Any]]:
    return [{"n": n, "date": first if i == 0 else "2024-05-20"} for i, n in enumerate(numbers)]


def corpus(large: bool) -> list[Case]:
    """The attacks' rules over states small enough for both to answer (and, with `large`, the 30,000 flights
    whose numbers hash alike, which both refuse)."""
    pairs = "{(x['date'], x['n']) for x in a} == {(x['date'], x['n']) for x in self.results['t'][b]}"
    generators = "all(all(all(g) for x in ((),)) for g in [(y['date'] >= '2024-05-15' for y in x) for x in (a,)])"
    last = "all(all(g) for g in [(f['date'] >= '2024-05-15' for y in (1,)) for f in a])"
    powers = "len([v*v*v*v*v*v*v*v for v in [w*w*w*w*w*w*w*w for w in [u*u*u*u*u*u*u*u for u in (c,)]]]) == 1"
    alike = _flights([7 + i * P for i in range(40)])
    found = [Case(squarings(26), {}, {}, None, ((), "r", 3)), Case(squarings(3), {}, {}, None, ((), "r", 3)),
             Case(powers, {}, {}, None, ((), "r", 3)), Case(powers, {}, {}, None, ((), "r", 2**70)),
             Case(pairs, {"t": {"r": {"flights": alike}}}, {}, None, (tuple(alike[:1]), "r", 0)),
             Case(pairs.replace("[b]", "[b]['flights']"), {"t": {"r": {"flights": alike}}}, {}, None,
                  (tuple(alike), "r", 0))]
    for rule in (generators, last):
        for first in ("2024-05-01", "2024-05-20"):
            found.append(Case(rule, {}, {}, None, (tuple(_flights([1, 2], first)), "r", 0)))
    total = "sum([x['n'] for x in self.results['t'][b]['flights']]) - sum(a) <= c"
    tables = {"t": {"r": {"flights": alike}, 7 + P: 1, 7: 2}}
    found += [  # a balance against a total: integers that hash alike, floats as Python sums them, large integers
        Case(total, tables, {}, None, ((0.1, 0.2, 2**70), "r", 0.6)),
        Case(total, {"t": {"r": {"flights": _flights([0.1, 0.2, 0.3])}}}, {}, None, ((0.6,), "r", 0)),
        Case(total, {"t": {"r": {"flights": _flights(["x"])}}}, {}, None, ((), "r", 0)),  # raises: 0 + 'x'
        Case("sum(x['n'] for x in a if x['date'] >= '2024-05-15') >= c", {}, {}, None,
             (tuple(_flights([0.1, 0.2, 0.3], "2024-05-01")), "r", 0.5)),
        Case("sum(self.results['t']) > 0", tables, {}, None, ((), "r", 0)),  # a table's keys: raises, 0 + 'r'
        Case("sum(a) == c", {}, {}, None, ((2**70, -(2**70), 1), "r", 1))]
    if large:
        many = _flights([7 + i * P for i in range(30_000)])
        found.append(Case(pairs.replace("[b]", "[b]['flights']"), {"t": {"r": {"flights": many}}}, {}, None,
                          (tuple(many[:1]), "r", 0)))
    return found


def test_generated_rules_are_judged_by_the_guard_as_python_judges_them(pytestconfig: pytest.Config) -> None:
    count = int(pytestconfig.getoption("guard_cases"))
    outcomes: Counter[str] = Counter()
    disagreements: list[str] = []

    def judged(case: Case) -> None:
        kind, disagreement = judge(case)
        outcomes[kind] += 1
        if disagreement is not None:
            disagreements.append(disagreement[:600])

    for case in corpus(large=count >= 1000):
        judged(case)
    assert outcomes["refused when stored"] == 1 and outcomes["judged"] >= 12, outcomes
    settings(max_examples=count, deadline=None, database=None,
             suppress_health_check=list(HealthCheck))(given(cases())(judged))()
    print(f"\nguard vs Python: {sum(outcomes.values()):,} cases, {len(disagreements)} disagreements; {dict(outcomes)}")
    assert not disagreements, "\n".join(disagreements[:5])
    assert outcomes["judged"] > count // 10 and outcomes["raised"] > count // 10, outcomes
