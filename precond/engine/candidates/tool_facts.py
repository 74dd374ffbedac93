"""What a tool-calling agent's demonstrations show, read statically (their literals replayed, never run): each
action's calls with the results known at that moment, which fields the reads' results hold and with which values.

`tool_conditions` and `tool_relations` propose conditions from these facts; nothing here is executed, so a
hostile demonstration can only make a fact wrong, which the sandbox's judging of every condition then shows."""

from __future__ import annotations

import ast
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

from precond.engine.spec import Spec
from precond_client.openai_log import records

RESULT_PARAMS = ("tool", "key", "ok", "value")
MAX_ENTRIES = 1000

Scalar = str | int | float | bool | None


@dataclass
class Seen:
    """One demonstrated call of an action: its arguments and the successful results known at that moment."""

    args: dict[str, object]
    results: dict[tuple[str, object], object]
    said: object = None
    """What the user said last before the call (`USER.says`)."""
    run: int = 0
    """The index of the run it was read from."""
    listed: dict[str, list[dict[str, object]]] = field(default_factory=dict)
    """tool → the records (dicts) its successful list results held so far (`self.seen`'s list results)."""


@dataclass(frozen=True)
class Move:
    """One field of a record a write's result showed: the value read before the write, the value after."""

    run: int
    read: str
    name: str
    before: str
    after: object


@dataclass
class ToolFacts:
    key_param: dict[str, str] = field(default_factory=dict)
    """tool → the parameter whose argument keys its results."""
    values: dict[str, dict[str, Counter[Scalar]]] = field(default_factory=dict)
    """tool → scalar field → how often each value occurs in its (dict) results."""
    lists: dict[str, set[str]] = field(default_factory=dict)
    """tool → fields whose value is a list."""
    seen: dict[str, list[Seen]] = field(default_factory=dict)
    """action name → its demonstrated calls."""
    mappings: dict[str, set[str]] = field(default_factory=dict)
    """tool → fields whose value is an object (a profile's payment methods by id)."""
    item_fields: dict[tuple[str, str], dict[str, Counter[Scalar]]] = field(default_factory=dict)
    """(tool, list field) → the scalar fields of its items (dicts) and their values."""
    now: str | None = None
    """The conversations' time (`options.now`): dates are compared with it."""
    records: dict[str, Counter[str]] = field(default_factory=dict)
    """tool → how many of its listed records (`self.seen[tool]`, dicts) hold each field, with the count of
    records under the empty name: a field every record holds can be read off all of them."""
    moves: dict[str, list[Move]] = field(default_factory=dict)
    """write → the string fields of the records read under its key, as read and as its successful result showed
    them, one per field and call."""
    dict_results: Counter[str] = field(default_factory=Counter)
    """tool → how many of its successful results were objects (dicts): a field every one of them held can be read
    off any of them in `self.seen[tool]`."""
    entries: set[str] = field(default_factory=set)
    """The names of the entries of the objects reads returned (a profile's payment methods by id), at most
    MAX_ENTRIES: what an item naming one of them refers to."""
    params: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """tool → its parameters (the spec's stubs), in the order a call passes them."""
    writes: frozenset[str] = frozenset()
    """The state-changing tools (the spec's `WRITES`), whose results are kept in `self.changes`."""
    demonstrated: int | None = None
    """How many of the runs read are demonstrations (the first ones; the others are runs of labelled calls);
    None: all of them."""

    def demonstrated_calls(self, action: str) -> list[Seen]:
        """The action's calls in demonstrations, not in the runs of labelled calls: what "at every demonstrated
        call" is about (a labelled call to refuse is where a condition fails, by design)."""
        return [c for c in self.seen.get(action, []) if self.demonstrated is None or c.run < self.demonstrated]


def tool_class(spec: Spec) -> str | None:
    """The class that has the `result(tool, key, ok, value)` observation, if the spec is a tool spec."""
    return next((m.cls for m in spec.methods.values()
                 if m.name == "result" and m.positional == RESULT_PARAMS and not m.stub), None)


def writes_of(spec: Spec) -> frozenset[str]:
    """The spec's `WRITES = (...)`: the tools whose results are changes, not reads."""
    for node in spec.tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and node.targets[0].id == "WRITES"):
            ok, value = _literal(node.value)
            if ok and isinstance(value, tuple | list | set | frozenset):
                return frozenset(v for v in value if isinstance(v, str))
    return frozenset()


def _literal(node: ast.expr) -> tuple[bool, object]:
    try:
        return True, ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
        return False, None


class _Replay:
    """Walks one demonstration's statements in order, keeping the results as the spec's observation would."""

    def __init__(self, facts: ToolFacts, params: dict[str, tuple[str, ...]], writes: frozenset[str],
                 run: int = 0) -> None:
        self.facts, self.params, self.writes, self.run = facts, params, writes, run
        self.results: dict[tuple[str, object], object] = {}
        self.pending: list[tuple[str, dict[str, object]]] = []
        self.said: object = None
        self.listed: dict[str, list[dict[str, object]]] = {}

    def statement(self, node: ast.stmt) -> None:
        call = node.value if isinstance(node, ast.Expr) else None
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)) or call.keywords:
            return
        parsed = [_literal(a) for a in call.args]
        if not all(ok for ok, _ in parsed):
            return
        values = [v for _, v in parsed]
        if call.func.attr == "result" and len(values) == len(RESULT_PARAMS):
            self.result(*values)
        elif call.func.attr == "says" and len(values) == 1:
            self.said = values[0]
        elif call.func.attr in self.params:
            args = dict(zip(self.params[call.func.attr], values, strict=False))
            self.facts.seen.setdefault(call.func.attr, []).append(Seen(args, dict(self.results), self.said, self.run,
                                                                     {t: list(r) for t, r in self.listed.items()}))
            self.pending.append((call.func.attr, args))

    def result(self, tool: object, key: object, ok: object, value: object) -> None:
        if not self.pending or not isinstance(tool, str):
            return
        called, args = self.pending.pop(0)
        if called == tool and tool in self.writes and ok is True and isinstance(value, dict):
            self._note_moves(tool, key, value)
        if called != tool or tool in self.writes:
            return
        if key is not None and tool not in self.facts.key_param:
            param = next((p for p, v in args.items() if v == key), None)
            if param is not None:
                self.facts.key_param[tool] = param
        if ok is True and isinstance(value, dict):
            self.results[(tool, key)] = value
            self.facts.dict_results[tool] += 1
            self._note_fields(tool, value)
        elif ok is True and isinstance(value, str | int) and not isinstance(value, bool):
            self.results[(tool, key)] = value  # an id a lookup found (`find_user_id_by_email`)
        if ok is True and isinstance(value, list):
            counts = self.facts.records.setdefault(tool, Counter())
            for record in records(value):
                counts[""] += 1
                if isinstance(record, dict):
                    self.listed.setdefault(tool, []).append(record)
                if isinstance(record, dict):
                    counts.update(k for k, v in record.items() if isinstance(k, str) and isinstance(v, str | int))

    def _note_moves(self, write: str, key: object, value: dict[object, object]) -> None:
        """The fields of the records read under the write's key, with the value read and the one its result
        shows."""
        for (read, read_key), record in self.results.items():
            if read_key == key and key is not None and isinstance(record, dict):
                for name, before in record.items():
                    if isinstance(name, str) and isinstance(before, str) and name in value:
                        self.facts.moves.setdefault(write, []).append(Move(self.run, read, name, before, value[name]))

    def _note_fields(self, tool: str, value: dict[object, object]) -> None:
        counts = self.facts.values.setdefault(tool, {})
        lists = self.facts.lists.setdefault(tool, set())
        mappings = self.facts.mappings.setdefault(tool, set())
        for name, item in value.items():
            if not isinstance(name, str):
                continue
            if isinstance(item, dict):
                mappings.add(name)
                self.facts.entries.update(k for k in list(item)[:MAX_ENTRIES - len(self.facts.entries)]
                                          if isinstance(k, str))
            if isinstance(item, list):
                lists.add(name)
                _note_items(self.facts.item_fields.setdefault((tool, name), {}), item)
            elif item is None or isinstance(item, str | int | float | bool):
                counts.setdefault(name, Counter())[item] += 1


def _note_items(fields: dict[str, Counter[Scalar]], items: list[object]) -> None:
    for item in items:
        if isinstance(item, dict):
            for name, value in item.items():
                if isinstance(name, str) and (value is None or isinstance(value, str | int | float | bool)):
                    fields.setdefault(name, Counter())[value] += 1


def read_facts(spec: Spec, cls: str, demos: Iterable[ast.Module]) -> ToolFacts:
    params = {m.name: m.positional for m in spec.methods.values() if m.cls == cls and m.stub}
    writes = writes_of(spec)
    facts = ToolFacts(params=params, writes=writes)
    for run, module in enumerate(demos):
        replay = _Replay(facts, params, writes, run)
        for node in module.body:
            replay.statement(node)
    return facts
