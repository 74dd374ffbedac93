"""A check judged in the gateway, with no queue and no sandbox, where no caller text is code to run.

When the spec is one a converter writes (`converted_spec`) and every rule is one the embedded guard's restricted
interpreter evaluates (`precond_client.rule_interpreter`: rules are compiled to closures over the state, never
run), the state a history builds is kept in Python here and each proposed call is judged as the sandbox judges
it: its rules on its own copy of that state, a rule that raises named in `error`, and the first history line
whose call broke its action's rules in `history_violation`. The answer is the worker's, field for field
(tests/service/test_interpreted_differential.py compares them on every fixture); `judged_by` says "interpreter".

* An OpenAI spec with a history of messages and tool calls `{name, arguments}`: the embedded guard itself
  (`precond_client.guard.Guard`) judges it: one evaluator for the agent's process and the gateway.
* An SGD spec (`converted_spec.SGDSpec`) with a history program (sent as code or rendered from events): each
  statement must be one of the two object creations (`user = USER()`, `system = SYSTEM(user)`) or a call of a
  method of a created object with constant arguments, matching its parameters; each observation's effect is read
  from its body (an assignment of a constant or a parameter), which the recogniser has matched to the converter's.

Anything else (another statement, a call the interpreter cannot take, a rule outside its grammar, rules on an
action that is not a stub) returns None: the check takes the queue and the sandbox, as before.
"""

from __future__ import annotations

import ast
from collections import OrderedDict, defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

from precond.gateway.converted_spec import OpenAISpec, SGDSpec, converted_spec
from precond_client import rule_interpreter as grammar
from precond_client.guard import RULE_CHARS, VIOLATION_CHARS, Guard, NotEmbeddable, clean
from precond_client.rule_interpreter import Evaluate, Frame, WorkExceeded
from precond_client.schemas import rule_status

JUDGED_BY = "interpreter"
REMEMBERED_SETS = 64
"""Compiled sets kept per process (the spec, its rules and labels, per tenant): a tenant's checks repeat them."""
REMEMBERED_SET_CHARS = 128_000
"""A set larger than this (its spec, rules and labels as text) is compiled for each check, never kept: at most
`REMEMBERED_SETS` of this size stay in a gateway process."""
LITERALS = (str, int, float, bool, type(None))
REMEMBERED_HISTORIES = 16
REMEMBERED_HISTORY_CHARS = 16_000
History = tuple[dict[str, tuple[str, SimpleNamespace]], str | None]
"""The objects a history made (name → class and state), and where it first broke a rule."""


def _false() -> bool:
    return False


@dataclass(frozen=True)
class _Method:
    """A method of an SGD spec class: a stub (an action, no effect), or an observation that assigns a constant or
    one of its parameters to an attribute of the object or to a key of one of its tables."""

    params: tuple[str, ...]
    stub: bool
    attribute: str = ""
    key: str | None = None
    """The parameter whose value is the table's key (`self.informed_slot[slot] = True`); None: the attribute."""
    value: Any = None
    from_param: str | None = None
    """The parameter whose value is assigned (`self.query_success = status`); None: `value`."""

    def apply(self, receiver: SimpleNamespace, args: Sequence[Any]) -> None:
        if self.stub:
            return
        value = args[self.params.index(self.from_param)] if self.from_param is not None else self.value
        if self.key is None:
            setattr(receiver, self.attribute, value)
        else:
            getattr(receiver, self.attribute)[args[self.params.index(self.key)]] = value


def _self_attribute(node: ast.expr) -> str | None:
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
        return node.attr
    return None


def _method(node: ast.FunctionDef) -> _Method:
    """The method's effect, read from the converter's one-assignment body (`converted_spec` matched it)."""
    params = tuple(a.arg for a in node.args.args[1:])
    body = node.body[0]
    if isinstance(body, ast.Pass):
        return _Method(params, True)
    assert isinstance(body, ast.Assign) and len(body.targets) == 1
    target, value = body.targets[0], body.value
    key = None
    if isinstance(target, ast.Subscript):
        assert isinstance(target.slice, ast.Name)
        key, target = target.slice.id, target.value
    attribute = _self_attribute(target)
    assert attribute is not None
    if isinstance(value, ast.Name):
        return _Method(params, False, attribute, key, from_param=value.id)
    assert isinstance(value, ast.Constant)
    return _Method(params, False, attribute, key, value.value)


def _constant(value: Any) -> Callable[[Any], Any]:
    return lambda given: value


def _initial(node: ast.ClassDef) -> dict[str, Callable[[Any], Any]]:
    """What `__init__` sets: a `defaultdict(lambda: False)`, a constant, or the object it is given."""
    init = next(item for item in node.body if isinstance(item, ast.FunctionDef) and item.name == "__init__")
    made: dict[str, Callable[[Any], Any]] = {}
    for statement in init.body:
        assert isinstance(statement, ast.Assign)
        attribute, value = _self_attribute(statement.targets[0]), statement.value
        assert attribute is not None
        if isinstance(value, ast.Call):
            made[attribute] = lambda given: defaultdict(_false)
        elif isinstance(value, ast.Name):
            made[attribute] = lambda given: given
        else:
            assert isinstance(value, ast.Constant)
            made[attribute] = _constant(value.value)
    return made


class SGDSet:
    """An SGD spec's classes and a set's compiled rules: a history's state and the calls' verdicts."""

    def __init__(self, spec: SGDSpec, preconditions: Mapping[str, Sequence[str]],
                 decided: Mapping[str, Mapping[str, str]]) -> None:
        self.classes = {cls.name: cls for cls in (spec.user, spec.system)}
        self.methods = {cls.name: {item.name: _method(item) for item in cls.body
                                   if isinstance(item, ast.FunctionDef) and item.name != "__init__"}
                        for cls in self.classes.values()}
        self.initial = {name: _initial(cls) for name, cls in self.classes.items()}
        tables = _tables(spec.user)
        user_shape = grammar.Shape("object", {a: grammar.TABLE if a in tables else grammar.VALUE
                                              for a in self.initial["USER"]})
        self.system_shape = grammar.Shape("object", {"user": user_shape, "query_success": grammar.VALUE})
        self.preconditions = {action: list(rules) for action, rules in preconditions.items()}
        self.decided = {action: dict(labels) for action, labels in decided.items()}
        self.rules = {action: [(text, self._compile(action, text)) for text in rules]
                      for action, rules in preconditions.items()}
        self.histories: OrderedDict[str, History | None] = OrderedDict()

    def _compile(self, action: str, text: str) -> Evaluate:
        cls, _, name = action.partition(".")
        method = self.methods.get(cls, {}).get(name)
        if cls != "SYSTEM" or method is None or not method.stub:
            raise grammar.OutsideGrammar(f"{action}: not an action the interpreter judges")
        return grammar.compile_rule(text, grammar.Scope(self.system_shape, method.params))

    def judge(self, history: str, calls: Sequence[str]) -> dict[str, Any] | None:
        """The worker's answer (`CheckResponse` as JSON), or None when the history or a call is not one of the
        forms read here."""
        try:
            read = self._remembered_history(history)
        except WorkExceeded:
            return None
        if read is None:
            return None
        objects, violation = read
        parsed = [_call(text, objects, self.methods) for text in calls]
        if any(p is None for p in parsed):
            return None
        try:
            results = [self._verdict(text, objects, p) for text, p in zip(calls, parsed, strict=True) if p is not None]
        except WorkExceeded:
            return None  # the sandbox judges rules past the interpreter's step budget, under its CPU limit
        return {"results": results, "history_violation": violation, "judged_by": JUDGED_BY}

    def _remembered_history(self, history: str) -> History | None:
        """`_history`, remembered for the last REMEMBERED_HISTORIES histories up to REMEMBERED_HISTORY_CHARS: an
        agent checks several calls after one history (the objects are never changed: each call copies them)."""
        if len(history) > REMEMBERED_HISTORY_CHARS:
            return self._history(history)
        if history in self.histories:
            self.histories.move_to_end(history)
            return self.histories[history]
        read = self.histories[history] = self._history(history)
        if len(self.histories) > REMEMBERED_HISTORIES:
            self.histories.popitem(last=False)
        return read

    def _new(self, cls: str, given: Any) -> SimpleNamespace:
        return SimpleNamespace(**{a: make(given) for a, make in self.initial[cls].items()})

    def _history(self, history: str) -> History | None:
        """The objects after the history, and where it first broke a rule. Judged as the sandbox judges it: on
        a second run of its own (`child.check._first_broken`), where what a rule reads of a table stays read,
        while the calls are judged after a run the rules never touched."""
        try:
            tree = ast.parse(history)
        except (SyntaxError, ValueError, RecursionError, MemoryError):
            return None
        objects: dict[str, tuple[str, SimpleNamespace]] = {}
        judged: dict[str, tuple[str, SimpleNamespace]] = {}
        lines = history.splitlines()
        violation: str | None = None
        for statement in tree.body:
            if isinstance(statement, ast.Assign):
                if not (self._create(statement, objects) and self._create(statement, judged)):
                    return None
                continue
            call = _statement_call(statement, objects, self.methods)
            if call is None:
                return None
            target, cls, name, args = call
            action = f"{cls}.{name}"
            if violation is None and self.rules.get(action):
                violation = self._broken(lines, statement.lineno, action, judged[target][1], args)
            self.methods[cls][name].apply(objects[target][1], args)
            self.methods[cls][name].apply(judged[target][1], args)
        return objects, violation

    def _create(self, statement: ast.Assign, objects: dict[str, tuple[str, SimpleNamespace]]) -> bool:
        """`name = USER()` or `name = SYSTEM(user)` (a USER made before): the objects a history creates."""
        target, value = statement.targets, statement.value
        if len(target) != 1 or not isinstance(target[0], ast.Name) or not isinstance(value, ast.Call):
            return False
        cls = value.func.id if isinstance(value.func, ast.Name) else None
        if cls == "USER" and not value.args and not value.keywords:
            objects[target[0].id] = ("USER", self._new("USER", None))
            return True
        given = value.args[0] if len(value.args) == 1 and not value.keywords else None
        if cls != "SYSTEM" or not isinstance(given, ast.Name) or objects.get(given.id, ("",))[0] != "USER":
            return False
        objects[target[0].id] = ("SYSTEM", self._new("SYSTEM", objects[given.id][1]))
        return True

    def _broken(self, lines: list[str], line: int, action: str, receiver: SimpleNamespace,
                args: tuple[Any, ...]) -> str | None:
        """As the sandbox judges a history (`child.check._first_broken`): on the live state, a rule that raises
        does not hold; in the engine's words (`engine.broken_text`)."""
        frame = Frame(receiver, args)
        failed = [text for text, evaluate in self.rules[action] if not _holds(evaluate, frame)]
        if not failed:
            return None
        call = lines[line - 1].strip() if 0 < line <= len(lines) else "?"
        rules = ", ".join(f"`{clean(rule, VIOLATION_CHARS)}`" for rule in failed)
        return f"history, line {line}: {call}: {action}'s rule{'s' if len(failed) > 1 else ''} {rules} did not hold"

    def _verdict(self, text: str, objects: Mapping[str, tuple[str, SimpleNamespace]],
                 parsed: tuple[str, str, str, tuple[Any, ...]]) -> dict[str, Any]:
        target, cls, name, args = parsed
        action = f"{cls}.{name}"
        receiver = _copied(objects)[target][1]  # its own copy, as the sandbox's unit has
        frame = Frame(receiver, args)
        violations: list[str] = []
        errors: list[str] = []
        for rule, evaluate in self.rules.get(action, ()):
            try:
                if not evaluate(frame):
                    violations.append(clean(rule, VIOLATION_CHARS))
            except WorkExceeded:
                raise
            except Exception as exc:  # a rule that raises is a broken rule, never a plain "not allowed"
                errors.append(f"precondition {clean(rule, RULE_CHARS)!r} of {action} raised "
                              f"{clean(type(exc).__name__, 100)}: {clean(str(exc))}")
        labels = self._labels(text, violations)
        return {"call": text, "action": action,
                "rule_status": rule_status(self.preconditions.get(action, []), self.decided.get(action, {})),
                "allowed": not violations and not errors, "violations": violations, "decided": labels,
                "error": clean("; ".join(errors)) if errors else None}

    def _labels(self, call: str, violations: list[str]) -> dict[str, str]:
        """How each violated rule was decided, read as the engine reads it (`engine._labelled`)."""
        if not violations or not self.decided:
            return {}
        labels = {rule: label for action, found in self.decided.items()
                  if self._is_method(action) and f".{action.partition('.')[2]}(" in call
                  for rule, label in found.items()}
        return {v: labels[v] for v in violations if v in labels}

    def _is_method(self, action: str) -> bool:
        cls, _, name = action.partition(".")
        return name in self.methods.get(cls, {})


def _copied(objects: Mapping[str, tuple[str, SimpleNamespace]]) -> dict[str, tuple[str, SimpleNamespace]]:
    """A copy of the objects as `copy.deepcopy` makes it, at a tenth of its cost: the state holds only constants,
    tables of constants (copied), and the objects themselves (each copied once, so `system.user is user` holds)."""
    made: dict[int, SimpleNamespace] = {}

    def copied(found: SimpleNamespace) -> SimpleNamespace:
        if id(found) not in made:
            made[id(found)] = SimpleNamespace(**{
                name: copied(value) if isinstance(value, SimpleNamespace) else
                value.copy() if isinstance(value, dict) else value for name, value in vars(found).items()})
        return made[id(found)]

    return {name: (cls, copied(found)) for name, (cls, found) in objects.items()}


def _tables(cls: ast.ClassDef) -> set[str]:
    init = next(item for item in cls.body if isinstance(item, ast.FunctionDef) and item.name == "__init__")
    return {attribute for s in init.body if isinstance(s, ast.Assign) and isinstance(s.value, ast.Call)
            for attribute in [_self_attribute(s.targets[0])] if attribute is not None}


def _holds(evaluate: Evaluate, frame: Frame) -> bool:
    try:
        return bool(evaluate(frame))
    except WorkExceeded:
        raise
    except Exception:  # as the sandbox judges a history: a rule that raises does not hold
        return False


def _arguments(call: ast.Call, params: tuple[str, ...]) -> tuple[Any, ...] | None:
    """Constant arguments, one per parameter, none by keyword: the forms a converter writes."""
    if call.keywords or len(call.args) != len(params):
        return None
    if not all(isinstance(a, ast.Constant) and isinstance(a.value, LITERALS) for a in call.args):
        return None
    return tuple(a.value for a in call.args if isinstance(a, ast.Constant))


def _method_call(node: ast.expr, objects: Mapping[str, tuple[str, SimpleNamespace]],
                 methods: Mapping[str, Mapping[str, _Method]]) -> tuple[str, str, str, tuple[Any, ...]] | None:
    """`name.method(constants)` on a created object: (name, class, method, arguments)."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and isinstance(node.func.value, ast.Name) and node.func.value.id in objects):
        return None
    target, name = node.func.value.id, node.func.attr
    cls = objects[target][0]
    method = methods[cls].get(name)
    args = None if method is None else _arguments(node, method.params)
    return None if args is None else (target, cls, name, args)


def _statement_call(statement: ast.stmt, objects: Mapping[str, tuple[str, SimpleNamespace]],
                    methods: Mapping[str, Mapping[str, _Method]]) -> tuple[str, str, str, tuple[Any, ...]] | None:
    return _method_call(statement.value, objects, methods) if isinstance(statement, ast.Expr) else None


def _call(text: str, objects: Mapping[str, tuple[str, SimpleNamespace]],
          methods: Mapping[str, Mapping[str, _Method]]) -> tuple[str, str, str, tuple[Any, ...]] | None:
    """A proposed call of an action (a SYSTEM stub) the interpreter judges; None for any other text."""
    if "\n" in text.strip():
        return None
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None
    found = _method_call(node, objects, methods)
    if found is None or found[1] != "SYSTEM" or not methods["SYSTEM"][found[2]].stub:
        return None
    return found


class _Remembered:
    """Compiled sets, least recently used first out; a set that cannot be compiled is remembered as None."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.sets: OrderedDict[tuple[str, ...], SGDSet | Guard | None] = OrderedDict()

    def get(self, key: tuple[str, ...], build: Callable[[], SGDSet | Guard | None]) -> SGDSet | Guard | None:
        if key in self.sets:
            self.sets.move_to_end(key)
            return self.sets[key]
        found = build()
        self.sets[key] = found
        if len(self.sets) > self.size:
            self.sets.popitem(last=False)
        return found


_REMEMBERED = _Remembered(REMEMBERED_SETS)


def _compiled(spec: str, preconditions: Mapping[str, Sequence[str]], decided: Mapping[str, Mapping[str, str]],
              tag: str) -> SGDSet | Guard | None:
    shape = converted_spec(spec, tag)
    if shape is None:
        return None
    try:
        if isinstance(shape, OpenAISpec):
            return Guard(spec, preconditions, decided)
        return SGDSet(shape, preconditions, decided)
    except (NotEmbeddable, grammar.OutsideGrammar):
        return None


def judged(spec: str, preconditions: Mapping[str, Sequence[str]], decided: Mapping[str, Mapping[str, str]],
           history: str | Sequence[Mapping[str, Any]], program: str, calls: Sequence[str | Mapping[str, Any]],
           lines: Sequence[str], tag: str) -> dict[str, Any] | None:
    """The check's answer (`CheckResponse` as JSON, `judged_by` "interpreter") when it can be judged here, else
    None. `history` and `calls` as sent, `program` and `lines` as rendered for the sandbox, both screened
    (`checks.check_check`) already; `tag`: the caller's, under which what is compiled is remembered."""
    rules = repr(sorted((a, tuple(r)) for a, r in preconditions.items()))
    labels = repr(sorted((a, sorted(d.items())) for a, d in decided.items()))
    if len(spec) + len(rules) + len(labels) > REMEMBERED_SET_CHARS:
        compiled = _compiled(spec, preconditions, decided, tag)
    else:
        compiled = _REMEMBERED.get((tag, spec, rules, labels), lambda: _compiled(spec, preconditions, decided, tag))
    if isinstance(compiled, SGDSet):
        return compiled.judge(program, lines)
    if isinstance(compiled, Guard) and isinstance(history, list) and (not history or "role" in history[0]) \
            and all(isinstance(c, Mapping) for c in calls):
        answer = compiled.check_actions(history, [c for c in calls if isinstance(c, Mapping)])
        if any(f"raised {WorkExceeded.__name__}:" in (v.error or "") for v in answer.results):
            return None  # the sandbox judges rules past the interpreter's step budget, under its CPU limit
        return {**answer.model_dump(mode="json"), "judged_by": JUDGED_BY}
    return None
