"""Static checks of a request's programs, run before any work is queued: parse only, never execute.

The gateway answers 422 from these at once (naming the field, e.g. `demonstrations[2]`, and the line)
instead of accepting a job that can only fail later; the engine runs the same checks, so the CLI and a
job that reaches a worker say the same thing. Everything here is `ast` and the standard library.
"""

from __future__ import annotations

import ast
import difflib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from types import MappingProxyType

from precond.programs.spec import Method, main_body, read_methods

INVALID_PROGRAM = "invalid_program"
UNKNOWN_ACTION = "unknown_action"
INVALID_INPUT = "invalid_input"
WORK_BUDGET = "work_budget"


@dataclass(frozen=True)
class Problem:
    """Why a request cannot be used: `type` and `field` become the API's error type and field."""

    type: str
    field: str
    message: str


class ProgramProblem(Exception):
    def __init__(self, problem: Problem) -> None:
        super().__init__(problem.message)
        self.problem = problem


def parse(source: str, field: str) -> ast.Module:
    """Parse untrusted source; every failure (syntax, nesting too deep, NUL bytes) is a ProgramProblem."""
    try:
        return ast.parse(source)
    except SyntaxError as exc:
        message = f"{field}, line {exc.lineno}: SyntaxError: {exc.msg}"
        raise ProgramProblem(Problem(INVALID_PROGRAM, field, message)) from exc
    except RecursionError as exc:
        raise too_deep(field) from exc
    except (ValueError, MemoryError) as exc:
        message = f"{field}: cannot be parsed: {type(exc).__name__}"
        raise ProgramProblem(Problem(INVALID_PROGRAM, field, message)) from exc


def too_deep(field: str) -> ProgramProblem:
    message = f"{field}: an expression is nested too deeply to be checked (split long chains such as 1+1+...+1)"
    return ProgramProblem(Problem(INVALID_PROGRAM, field, message))


def spec_methods(source: str) -> tuple[ast.Module, dict[str, Method]]:
    tree = parse(source, "spec")
    methods = read_methods(tree)
    if not methods:
        message = "spec: defines no class with methods, so there are no actions"
        raise ProgramProblem(Problem(INVALID_PROGRAM, "spec", message))
    return tree, methods


REMEMBERED_SPEC_CHARS = 64_000
"""Specs up to this size are read once per scope; the memory kept is bounded by 32 of them."""


def remembered_spec_methods(scope: str, source: str) -> tuple[ast.Module, dict[str, Method]]:
    """`spec_methods`, remembered per scope: a tenant's guard sends the same spec with every check. Read only."""
    return _remembered(scope, source) if len(source) <= REMEMBERED_SPEC_CHARS else spec_methods(source)


@lru_cache(maxsize=32)
def _remembered(_scope: str, source: str) -> tuple[ast.Module, dict[str, Method]]:
    return spec_methods(source)


REMEMBERED_HISTORY_CHARS = 16_000
"""Histories up to this size have their receivers read once per scope (`history_receivers`); the memory kept is
bounded by 256 of them."""


def history_receivers(scope: str, classes: frozenset[str], history: str) -> Mapping[str, str]:
    """`instance_classes` of a history, which must parse (ProgramProblem), remembered per scope and text for
    histories up to `REMEMBERED_HISTORY_CHARS`: a guard checks several calls against one history, and the
    gateway's screen and the worker both read it. Read only."""
    if len(history) > REMEMBERED_HISTORY_CHARS:
        return instance_classes([parse(history, "history")], set(classes))
    return _remembered_receivers(scope, classes, history)


@lru_cache(maxsize=256)
def _remembered_receivers(_scope: str, classes: frozenset[str], history: str) -> Mapping[str, str]:
    return MappingProxyType(instance_classes([parse(history, "history")], set(classes)))


MAX_SUGGESTION_CHARS = 100
MAX_SUGGESTION_CANDIDATES = 200
"""Bounds of the "did you mean" search: difflib's cost grows with the product of the lengths, so a long unknown
name against 900 long method names held the gateway for seconds. Past them the hint is left out."""


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """" (did you mean 'SYSTEM.REQUEST'?)" for the closest known name, or "" when none is close."""
    if len(name) > MAX_SUGGESTION_CHARS:
        return ""
    near = [k for k in known if len(k) <= 2 * MAX_SUGGESTION_CHARS][:MAX_SUGGESTION_CANDIDATES]
    close = difflib.get_close_matches(name, near, n=1, cutoff=0.6)
    if not close and "." not in name:  # `REQUEST` for `SYSTEM.REQUEST`: compare the method names
        close = [k for k in known if k.rsplit(".", 1)[-1] == name][:1]
    return f" (did you mean {close[0]!r}?)" if close else ""


def unknown_action(name: str, methods: Mapping[str, Method], field: str, where: str = "") -> ProgramProblem:
    known = ", ".join(sorted(methods)[:20])
    message = f"unknown action {name!r}{where}{did_you_mean(name, methods)}; the spec defines: {known}"
    return ProgramProblem(Problem(UNKNOWN_ACTION, field, message))


def resolve_actions(methods: Mapping[str, Method], requested: Sequence[str] | None) -> list[str]:
    """Requested names must exist; by default every stub method is an action."""
    if requested is None:
        actions = [name for name, method in methods.items() if method.stub]
        if not actions:
            message = "spec has no stub methods (body only pass/.../docstring); name the actions"
            raise ProgramProblem(Problem(UNKNOWN_ACTION, "actions", message))
        return actions
    for index, name in enumerate(requested):
        if name not in methods:
            raise unknown_action(name, methods, f"actions[{index}]")
    return list(dict.fromkeys(requested))


def expression_hint(text: str) -> str | None:
    """A hint for a rule that is not an expression but is easily made one (`assert x` → `x`)."""
    stripped = text.strip()
    if stripped.startswith("assert") and stripped[6:7] in (" ", "(", "\t"):
        return "write the expression without `assert` (e.g. `self.open`, not `assert self.open`)"
    return None


def expression_problem(text: str) -> str | None:
    """Why a rule is not one Python expression, or None."""
    try:
        ast.parse(text, mode="eval")
    except SyntaxError as exc:
        hint = expression_hint(text)
        return f"not a single expression: {hint or exc.msg}"
    except (ValueError, RecursionError, MemoryError) as exc:
        return f"not a single expression: cannot be parsed: {type(exc).__name__}"
    return None


REMEMBERED_RULES_CHARS = 64_000
"""Rules up to this size (all expressions together) that passed are remembered per scope and spec; the memory
kept is bounded by 64 such sets."""


def remembered_check_preconditions(scope: str, spec: str, methods: Mapping[str, Method],
                                   preconditions: Mapping[str, Sequence[str]]) -> None:
    """`check_preconditions` against `spec`'s `methods`, its success remembered per scope, spec and rules: a
    guard sends the same rules, or names the same stored set, with every check, and each rule is parsed again in
    the gateway's screen and in the worker (some 8 µs a rule; a learned SGD set has 20-40). A failure is never
    remembered: the same rules fail again with the same problem."""
    rules = tuple((name, tuple(expressions)) for name, expressions in preconditions.items())
    if len(spec) > REMEMBERED_SPEC_CHARS or sum(len(e) for _, es in rules for e in es) > REMEMBERED_RULES_CHARS:
        check_preconditions(methods, preconditions)
        return
    _remembered_passing_rules(scope, spec, rules)


@lru_cache(maxsize=64)
def _remembered_passing_rules(scope: str, spec: str, rules: tuple[tuple[str, tuple[str, ...]], ...]) -> bool:
    check_preconditions(remembered_spec_methods(scope, spec)[1], dict(rules))
    return True


def check_preconditions(methods: Mapping[str, Method], preconditions: Mapping[str, Sequence[str]]) -> None:
    for name, expressions in preconditions.items():
        if name not in methods:
            raise unknown_action(name, methods, f"preconditions.{name}", " in preconditions")
        for index, expression in enumerate(expressions):
            problem = expression_problem(expression)
            if problem is not None:
                field = f"preconditions.{name}[{index}]"
                raise ProgramProblem(Problem(INVALID_PROGRAM, field, f"{field}: {problem}"))


def instance_classes(trees: Iterable[ast.Module], classes: set[str]) -> dict[str, str]:
    """`system = SYSTEM(user)` → {"system": "SYSTEM"}: how a call's receiver maps to a spec class."""
    found: dict[str, str] = {}
    for tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
                func = node.value.func
                if isinstance(func, ast.Name) and func.id in classes:
                    found.update({t.id: func.id for t in node.targets if isinstance(t, ast.Name)})
    return found


def called_actions(trees: Sequence[ast.Module], methods: Mapping[str, Method], actions: Iterable[str]) -> set[str]:
    """The actions some program calls, read statically. Lenient: a call on a receiver whose class is not
    known from an assignment counts for every action of that method name (the sandbox's trace is exact)."""
    wanted = set(actions)
    receivers = instance_classes(trees, {m.cls for m in methods.values()})
    by_name: dict[str, set[str]] = {}
    for action in wanted:
        by_name.setdefault(methods[action].name, set()).add(action)
    found: set[str] = set()
    for tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in by_name:
                receiver = node.func.value
                cls = receivers.get(receiver.id) if isinstance(receiver, ast.Name) else None
                matching = by_name[node.func.attr]
                found |= matching if cls is None else {a for a in matching if methods[a].cls == cls}
    return found


def no_occurrence_problem(actions: Sequence[str], count: int) -> ProgramProblem:
    names = ", ".join(actions[:10]) + (", ..." if len(actions) > 10 else "")
    message = (f"demonstrations: none of the {count} demonstrations calls any of the actions ({names}), so "
               "there is no evidence to infer a rule from; add demonstrations that call them")
    return ProgramProblem(Problem(INVALID_INPUT, "demonstrations", message))


def check_work(trees: Sequence[ast.Module], max_points: int | None) -> None:
    """The work a request asks for, from its text: every candidate is judged at every point of its action,
    demonstration steps x the distinct argument tuples it was called with. That product, not the body's
    size, is what costs (37 KB with 3,000 distinct calls make 9 million points); the sandbox bounds the exact
    count again inside its child."""
    if max_points is None:
        return
    steps = sum(len(main_body(tree)) for tree in trees)
    arguments: dict[str, set[str]] = {}
    for index, tree in enumerate(trees):
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                call = ast.Call(func=ast.Name("f"), args=node.args, keywords=node.keywords)
                try:  # ast.dump recurses: a flat chain of 1,500 additions parses, yet overflows it
                    arguments.setdefault(node.func.attr, set()).add(ast.dump(call))
                except RecursionError:
                    raise too_deep(f"demonstrations[{index}]") from None
    if not arguments:
        return
    method, values = max(arguments.items(), key=lambda item: len(item[1]))
    if steps * len(values) > max_points:
        message = (f"about {steps * len(values):,} points to judge every candidate at ({steps:,} demonstration "
                   f"steps x {len(values):,} distinct argument tuples of .{method}(...)), over the budget of "
                   f"{max_points:,} (PRECOND_MAX_WORK_POINTS): send fewer demonstrations or fewer distinct "
                   "arguments")
        raise ProgramProblem(Problem(WORK_BUDGET, "demonstrations", message))


def check_infer(spec: str, demonstrations: Sequence[str], actions: Sequence[str] | None,
                max_points: int | None = None) -> None:
    """Everything an inference needs that can be seen without running it; raises ProgramProblem."""
    _, methods = spec_methods(spec)
    chosen = resolve_actions(methods, actions)
    trees = [parse(d, f"demonstrations[{i}]") for i, d in enumerate(demonstrations)]
    if not called_actions(trees, methods, chosen):
        raise no_occurrence_problem(chosen, len(demonstrations))
    check_work(trees, max_points)


def check_training(spec: str, demonstrations: Sequence[str]) -> None:
    """A policy training's request, seen without running it: the spec and every demonstration parse, and at
    least one demonstration calls an action (the lines the loss is taken on); raises ProgramProblem."""
    _, methods = spec_methods(spec)
    actions = resolve_actions(methods, None)
    trees = [parse(d, f"demonstrations[{i}]") for i, d in enumerate(demonstrations)]
    if not called_actions(trees, methods, actions):
        names = ", ".join(actions[:10]) + (", ..." if len(actions) > 10 else "")
        message = (f"demonstrations: none of the {len(demonstrations)} demonstrations calls any of the actions "
                   f"({names}): a policy is trained on those calls (its action lines), so there is nothing to "
                   "train on")
        raise ProgramProblem(Problem(INVALID_INPUT, "demonstrations", message))


def check_prior_rules(sources: Sequence[tuple[str, Mapping[str, Sequence[str]]]]) -> None:
    """Each prior rule (`sources`: the field that holds them, and action -> rules) is one expression that calls
    nothing but methods reached from `self` (a spec's query); raises ProgramProblem naming the rule."""
    for where, table in sources:
        for action, rules in table.items():
            for index, rule in enumerate(rules):
                problem = expression_problem(rule)
                if problem is None and any(_foreign_call(n) for n in ast.walk(ast.parse(rule.strip(), mode="eval"))):
                    problem = ("calls something other than a method of the state (a prior is a condition over the "
                               "state and the action's arguments)")
                if problem is not None:
                    field = f"{where}[{action}][{index}]"
                    raise ProgramProblem(Problem(INVALID_PROGRAM, field, f"{field}: {problem}"))


def check_infer_with_priors(spec: str, demonstrations: Sequence[str], actions: Sequence[str] | None,
                            max_points: int | None,
                            priors: Sequence[tuple[str, Mapping[str, Sequence[str]]]] = ()) -> None:
    """`check_infer`, then the request's prior rules (`check_prior_rules`): one call for the gateway's check pool."""
    check_infer(spec, demonstrations, actions, max_points)
    check_prior_rules(priors)


def _foreign_call(node: ast.AST) -> bool:
    """A call of anything but a method reached from `self` (`self.is_visible(obj)`), or code that defines or
    binds something."""
    if isinstance(node, ast.Lambda | ast.NamedExpr):
        return True
    if not isinstance(node, ast.Call):
        return False
    func = node.func
    while isinstance(func, ast.Attribute):
        func = func.value
    return not (isinstance(func, ast.Name) and func.id == "self" and isinstance(node.func, ast.Attribute))


def check_next_action(spec: str, preconditions: Mapping[str, Sequence[str]], demonstrations: Sequence[str],
                      history: str, max_points: int | None = None) -> None:
    _, methods = spec_methods(spec)
    check_preconditions(methods, preconditions)
    trees = [parse(d, f"demonstrations[{i}]") for i, d in enumerate(demonstrations)]
    parse(history, "history")
    check_work(trees, max_points)


def check_set(spec: str, preconditions: Mapping[str, Sequence[str]], demonstrations: Sequence[str]) -> None:
    """A precondition set's version: the spec, every rule (known action, one expression), the demonstrations."""
    _, methods = spec_methods(spec)
    check_preconditions(methods, preconditions)
    for index, demonstration in enumerate(demonstrations):
        parse(demonstration, f"demonstrations[{index}]")


def check_reinfer(spec: str, new: Sequence[str], union: Sequence[str], actions: Sequence[str] | None,
                  max_points: int | None) -> None:
    """A re-inference: its new demonstrations (named by their index in the request), then the inference on the
    union of the stored and the new ones."""
    for index, demonstration in enumerate(new):
        parse(demonstration, f"demonstrations[{index}]")
    check_infer(spec, union, actions, max_points)


def check_check(spec: str, preconditions: Mapping[str, Sequence[str]], history: str,
                calls: Sequence[str] = (), scope: str = "") -> None:
    """`scope`: whose check this is; the spec's reading is remembered per scope (`remembered_spec_methods`)."""
    _, methods = remembered_spec_methods(scope, spec)
    remembered_check_preconditions(scope, spec, methods, preconditions)
    check_calls(methods, preconditions, history_receivers(scope, spec_classes(methods), history), calls)


def _literal_arguments(call: ast.Call) -> bool:
    """Arguments the sandbox accepts (literals, no `*`/`**`); a call with others it refuses itself."""
    try:
        for value in [*call.args, *(k.value for k in call.keywords if k.arg is not None)]:
            ast.literal_eval(value)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return False
    return all(k.arg is not None for k in call.keywords)


def _received_call(receivers: Mapping[str, str], text: str) -> tuple[ast.Call, str] | None:
    """`text` parsed as a `receiver.method(...)` whose receiver the history binds, and its `Class.method`."""
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name)
            and node.func.value.id in receivers):
        return node, f"{receivers[node.func.value.id]}.{node.func.attr}"
    return None


def called_action(methods: Mapping[str, Method], receivers: Mapping[str, str], text: str) -> str | None:
    """The spec method (`Class.method`) a proposed call calls, when it is a call of one on a receiver the
    history binds; None for any other text (the sandbox refuses it with the reason)."""
    found = _received_call(receivers, text)
    return found[1] if found is not None and found[1] in methods else None


def spec_classes(methods: Mapping[str, Method]) -> frozenset[str]:
    return frozenset(m.cls for m in methods.values())


def check_calls(methods: Mapping[str, Method], preconditions: Mapping[str, Sequence[str]],
                receivers: Mapping[str, str], calls: Sequence[str]) -> None:
    """Every proposed `receiver.method(...)` whose receiver the history creates must be a call of one of the
    agent's actions (the spec's stubs and the actions given rules): a method its class lacks is an unknown action
    (with the closest name), and a method that is not an action (an observation, the user's `AFFIRM`) is
    refused, never approved because no rule guards it. Text that is not such a call (with literal arguments)
    is left to the sandbox, which refuses it with the reason. `receivers`: the history's (`history_receivers`)."""
    actions = {name for name, method in methods.items() if method.stub} | set(preconditions)
    for index, text in enumerate(calls):
        found = _received_call(receivers, text)
        if found is None or not _literal_arguments(found[0]):
            continue
        name, field = found[1], f"calls[{index}]"
        if name not in methods:
            raise unknown_action(name, {a: methods[a] for a in actions if a in methods}, field, f" in {field}")
        if name not in actions:
            known = ", ".join(sorted(actions)[:20])
            message = (f"{field}: {name} is not one of the agent's actions (a spec method with a body, not a stub, "
                       f"and no rule given), so no precondition can judge it; the actions: {known}")
            raise ProgramProblem(Problem(UNKNOWN_ACTION, field, message))


def normal(rule: str) -> str:
    """A rule's canonical text (`ast.unparse`): `x["a"]` and `x['a']`, or `self.a and  self.b` and
    `self.a and self.b`, are one rule wherever rules are compared (sets, re-inference, priors)."""
    try:
        return ast.unparse(ast.parse(rule.strip(), mode="eval"))
    except (SyntaxError, ValueError, RecursionError):
        return rule.strip()
