"""OpenAI chat logs of a tool-calling agent → spec, demonstration programs (docs/converting.md).

The spec is derived from the tools' JSON schemas: one action (a stub of AGENT) per tool, its parameters in
the schema's order; two observations: `user.says(text)` for a user message and `agent.result(tool, key, ok,
value)` for a tool's result, which keeps the parsed JSON result in `agent.results[tool][key]` (errors in
`agent.errors`), `key` being the call's identifying argument (its first `*_id` parameter), so that a rule can
say "a successful read of *this* reservation came before this write". Calls and results are paired by position
(tool-call ids repeat in real logs). Arguments and results are JSON, read by `precond_client.openai_log` (which
the embedded guard shares) and written with `repr` as literals: nothing in a log can become code. Standard
library, `precond/programs/` and that module only: the gateway renders histories with it.
"""

from __future__ import annotations

import ast
import keyword
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

from precond.programs import checks
from precond.programs.history import render as render_events
from precond.programs.names import python_name
from precond_client.openai_log import (
    MAX_SEEN,
    PREAMBLE,
    RESERVED,
    RESERVED_PARAMETERS,
    SCHEMAS,
    Call,
    PlaceError,
    Reader,
    Tool,
    call_line,
    parse_json,
    read_schemas,
    records,
    spec_program,
    writes_of,
)
from precond_client.schemas.tool_schemas import schema_error, schema_problem


@dataclass(frozen=True)
class CallLabel:
    """A label a log carries on the tool call itself (`"label": "refuse"` in an assistant's `tool_calls` entry)."""

    message: int
    position: int
    """Which call of that message (a message may make several)."""
    allowed: bool
    where: str


@dataclass
class Trajectory:
    name: str
    program: str
    calls: list[Call] = field(default_factory=list)
    reward: float | None = None
    messages: list[int] = field(default_factory=list)
    """The index of the message that made each call (labels name calls so)."""
    labels: list[CallLabel] = field(default_factory=list)


@dataclass
class Converted:
    spec: str
    tools: list[Tool]
    writes: set[str]
    """The state-changing tools: their results go to `self.changes`, a read's to `self.results`."""
    trajectories: list[Trajectory] = field(default_factory=list)
    guarded: set[str] = field(default_factory=set)
    """The tools rules are inferred for (the request's actions): every tool unless told otherwise. A read is
    guarded as a write is (reading another customer's order breaks a policy too)."""

    @property
    def without_writes(self) -> int:
        """Trajectories with no state-changing call: accepted and counted, never dropped silently."""
        return sum(1 for t in self.trajectories if not any(c.tool in self.writes for c in t.calls))

    @property
    def past_seen(self) -> int:
        """Trajectories in which a read tool listed more than MAX_SEEN records: `self.seen` keeps the last
        MAX_SEEN of them, and the command says so, never dropping them silently."""
        def over(trajectory: Trajectory) -> bool:
            listed: Counter[str] = Counter()
            for call in trajectory.calls:
                if call.tool not in self.writes and call.result is not None and call.result[0]:
                    listed[call.tool] += len(records(call.result[1]))
            return any(n > MAX_SEEN for n in listed.values())
        return sum(1 for t in self.trajectories if over(t))


def _fail(where: str, message: str) -> PlaceError:
    return PlaceError(where, message)


def _identifier(name: object, where: str, what: str) -> str:
    """The name as Python reads it (`python_name`), once it is one the spec may define."""
    read = python_name(name) if isinstance(name, str) else None
    if read is None or not read.isidentifier() or keyword.iskeyword(read) or read.startswith("_"):
        raise _fail(where, f"{what} {read if read is not None else name!r} cannot be a Python name (letters, "
                    "digits, _; not a keyword)")
    return read


def read_tools(data: Any, source: str) -> list[Tool]:
    """OpenAI function schemas (`{"type": "function", "function": {...}}`, or the bare function objects)."""
    if not isinstance(data, list) or not data:
        raise _fail(source, "expected a non-empty list of tool schemas")
    tools: dict[str, Tool] = {}
    for index, raw in enumerate(data):
        where = f"{source}: [{index}]"
        function = raw.get("function", raw) if isinstance(raw, dict) else None
        if not isinstance(function, dict):
            raise _fail(where, "expected an object with 'function' (an OpenAI tool schema)")
        name = _identifier(function.get("name"), f"{where}.function.name", "tool name")
        if name in RESERVED or name in tools:
            raise _fail(f"{where}.function.name", f"{name!r} is {'reserved' if name in RESERVED else 'listed twice'}")
        parameters = function.get("parameters") or {}
        properties = parameters.get("properties", {}) if isinstance(parameters, dict) else None
        required = parameters.get("required", []) if isinstance(parameters, dict) else None
        if not isinstance(properties, dict) or not isinstance(required, list):
            raise _fail(f"{where}.function.parameters", "expected {'properties': {...}, 'required': [...]}")
        params: dict[str, str] = {}
        for param in properties:
            read = _identifier(param, f"{where}.function.parameters.properties", "parameter")
            if read in RESERVED_PARAMETERS or read in params.values():
                problem = "is reserved" if read in RESERVED_PARAMETERS else "is listed twice"
                raise _fail(f"{where}.function.parameters.properties", f"parameter {read!r} {problem}")
            params[param] = read
        unknown = [r for r in required if r not in properties]
        if unknown:
            raise _fail(f"{where}.function.parameters.required", f"{unknown[0]!r} is not among its properties")
        required = [params[r] for r in required]
        ordered = [p for p in params.values() if p in required] + [p for p in params.values() if p not in required]
        description = function.get("description")
        invalid = schema_error(parameters) if parameters else None
        if invalid is not None:
            raise _fail(f"{where}.function.parameters", f"not a JSON Schema: {invalid}")
        tools[name] = Tool(name, tuple(ordered), frozenset(required),
                           description if isinstance(description, str) else "", parameters or None)
    return list(tools.values())


class Renderer(Reader):
    """One trajectory's messages → program lines, calls paired with results by position."""

    def __init__(self, tools: Sequence[Tool], where: str) -> None:
        super().__init__(tools, where)
        self.lines: list[str] = list(PREAMBLE)
        self.calls: list[Call] = []
        self.messages: list[int] = []
        self._at = -1

    def message(self, index: int, message: Any) -> None:
        self._at = index
        super().message(index, message)

    def said(self, text: str | None) -> None:
        self.lines.append(f"user.says({text!r})")

    def called(self, call: Call) -> None:
        self.lines.append(call_line(call, self.tools[call.tool]))
        self.calls.append(call)
        self.messages.append(self._at)

    def answered(self, call: Call) -> None:
        ok, value = call.result or (False, None)
        self.lines.append(f"agent.result({call.tool!r}, {call.key!r}, {ok}, {value!r})")

    def line(self, call: Any, at: str) -> str:
        """A call as `agent.tool(args...)`; also what the gateway makes of a proposed `{name, arguments}`."""
        self.call(call, at)
        return self.lines[-1]

    def program(self) -> str:
        return "\n".join(self.lines) + "\n"


def render(messages: Any, tools: Sequence[Tool], where: str) -> Renderer:
    if not isinstance(messages, list):
        raise _fail(where, f"expected a list of OpenAI chat messages, found {type(messages).__name__}")
    renderer = Renderer(tools, where)
    for index, message in enumerate(messages):
        renderer.message(index, message)
    return renderer


def _runs(data: Any, source: str) -> list[tuple[str, Any, str, float | None]]:
    """(name, messages, where, reward) per trajectory: a list of messages is one; a list of lists or of
    tau-bench records (`{"traj": [...]}`) is several; one record is one."""
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data:
        raise _fail(source, "expected a list of messages, of trajectories, or of {'traj': [...]} records")
    if all(isinstance(m, dict) and "role" in m for m in data):
        return [("0", data, f"{source}: ", None)]
    runs: list[tuple[str, Any, str, float | None]] = []
    for n, item in enumerate(data):
        if isinstance(item, list):
            runs.append((str(n), item, f"{source}: [{n}]", None))
        elif isinstance(item, dict) and "traj" in item:
            name = _record_name(item, n)
            runs.append((name, item["traj"], f"{source}: [{n}].traj", _reward(item.get("reward"), f"{source}: [{n}]")))
        else:
            raise _fail(f"{source}: [{n}]", "expected a list of messages or a {'traj': [...]} record")
    return runs


def _reward(value: Any, where: str) -> float | None:
    """A record's reward as a finite float (None when it has none); a number that is not one is refused."""
    if not isinstance(value, int | float):
        return None
    try:
        reward = float(value)
    except OverflowError:
        reward = math.inf
    if not math.isfinite(reward):
        raise _fail(f"{where}.reward", "not a finite number")
    return reward


def _record_name(record: dict[str, Any], index: int) -> str:
    task, trial = record.get("task_id"), record.get("trial")
    if isinstance(task, int | str) and isinstance(trial, int | str):
        return f"task{task}-trial{trial}"
    return str(index)


def convert(data: Any, tools_data: Any, source: str = "trajectories", tools_source: str = "tools",
            writes: set[str] | None = None, guarded: set[str] | None = None) -> Converted:
    """Parsed trajectories and tool schemas → the spec and one program per trajectory. `writes`: the
    state-changing tools (default: named like writes, `writes_of`); `guarded`: the tools to infer rules for
    (default: all of them)."""
    tools = read_tools(tools_data, tools_source)
    names = {t.name for t in tools}
    chosen = writes_of(tools) if writes is None else writes
    for what, given in (("state-changing", chosen), ("guarded", guarded or set())):
        unknown = sorted(given - names)
        if unknown:
            raise _fail(tools_source, f"{what} tool {unknown[0]!r} is not among the tools")
    converted = Converted(spec_program(tools, chosen), tools, chosen, guarded=set(names if guarded is None
                                                                                    else guarded))
    for name, messages, where, reward in _runs(data, source):
        renderer = render(messages, tools, where)
        converted.trajectories.append(Trajectory(name, renderer.program(), renderer.calls, reward, renderer.messages,
                                                 _call_labels(messages, where)))
    return converted


CALL_LABELS = {"refuse": False, "allow": True}


def _call_labels(messages: list[Any], where: str) -> list[CallLabel]:
    """The labels the calls carry (`"label": "refuse"` or `"allow"` beside `function`); any other value is
    refused naming it: a label read wrong would be a silently weaker guard. The messages were read already."""
    found = []
    for index, message in enumerate(messages):
        calls = (message.get("tool_calls") or []) if message.get("role") == "assistant" else []
        for position, call in enumerate(calls):
            if not isinstance(call, dict) or "label" not in call:
                continue
            at = f"{where}[{index}].tool_calls[{position}].label"
            allowed = CALL_LABELS.get(call["label"]) if isinstance(call["label"], str) else None
            if allowed is None:
                raise _fail(at, f"expected 'refuse' or 'allow', found {call['label']!r}")
            found.append(CallLabel(index, position, allowed, at))
    return found


# ---- inside the API: histories and calls of a check or next-action request ---------------------------------

def spec_tools(spec: str, field: str, scope: str = "") -> tuple[Tool, ...]:
    """The tools of a spec `precond convert openai` wrote: AGENT's stubs, their parameters as declared. `scope`:
    whose spec (the tenant), under which its reading is remembered."""
    tools = _tools_of(spec, scope)
    if tools is None:
        raise _fail(field, "OpenAI messages and tool calls need a spec made by `precond convert openai` (class AGENT "
                    "with result(tool, key, ok, value), class USER with says(text))")
    return tools


def _tools_of(spec: str, scope: str) -> tuple[Tool, ...] | None:
    """Read per scope (`checks.remembered_spec_methods`): a guard sends its spec with every check, and a reading
    shared by the tenants would let one tell, by the time its own check takes, that another sent the same spec
    (docs/security.md)."""
    _, methods = checks.remembered_spec_methods(scope, spec)
    if not any(m.qualname == "AGENT.result" and not m.stub for m in methods.values()) or "USER.says" not in methods:
        return None
    return tuple(Tool(m.name, m.positional, frozenset(m.positional[: len(m.positional) - len(m.node.args.defaults)]))
                 for m in methods.values() if m.cls == "AGENT" and m.stub)


def _problem(exc: PlaceError) -> checks.ProgramProblem:
    return checks.ProgramProblem(checks.Problem(checks.INVALID_INPUT, exc.where, str(exc)))


def structured_history(spec: str, history: Sequence[Mapping[str, Any]], field: str = "history",
                       scope: str = "") -> str:
    """Events (`{actor, act, args}`) or OpenAI chat messages (`{role, ...}`) → the program; bad input raises
    `ProgramProblem` naming the field (`history[3].tool_calls[0].arguments`), as events always did. `scope`:
    whose history (`programs.history.render`)."""
    if not (history and "role" in history[0]):
        return render_events(spec, history, field, scope)
    try:
        return render(list(history), spec_tools(spec, field, scope), field).program()
    except PlaceError as exc:
        raise _problem(exc) from None


def call_lines(spec: str, calls: Sequence[str | Mapping[str, Any]], field: str = "calls",
               scope: str = "") -> list[str]:
    """Proposed calls as program lines: code as sent, tool calls `{name, arguments}` rendered with literals.
    `scope`: whose calls (`spec_tools`)."""
    if all(isinstance(c, str) for c in calls):
        return [c for c in calls if isinstance(c, str)]
    try:
        renderer = Renderer(spec_tools(spec, field, scope), field)
        return [c if isinstance(c, str) else renderer.line(dict(c), f"{field}[{n}]") for n, c in enumerate(calls)]
    except PlaceError as exc:
        raise _problem(exc) from None


def holds_schemas(spec: str) -> bool:
    """Whether the spec keeps its tools' JSON Schemas (`SCHEMAS = ...`, as `precond convert openai` writes it)."""
    return f"\n{SCHEMAS} = " in spec


def call_schema_problems(spec: str, calls: Sequence[str | Mapping[str, Any]], scope: str = "") -> list[str | None]:
    """Per proposed call, why its arguments break its tool's JSON Schema (`tool_schemas`), None when they keep it
    (or its tool has none, or it is code other than one call of a tool with literal arguments); a spec whose
    `SCHEMAS` cannot be read refuses every tool call (fail closed). The calls have been read (`call_lines`): each
    names a tool of the spec, with a JSON object, or is code. A call sent as code (`agent.cancel_order('#W1',
    'too_expensive')`) is the same call as its JSON form, and keeps the same schema."""
    if not holds_schemas(spec):
        return [None] * len(calls)
    schemas = _schemas_of(scope, spec)
    problems: list[str | None] = []
    for call in calls:
        found = _code_call(spec, call, scope) if isinstance(call, str) else _json_call(call)
        if found is None:
            problems.append(None)
            continue
        name, arguments = found
        problems.append(schemas if isinstance(schemas, str) else
                        schema_problem(name, schemas[name], arguments) if name in schemas else None)
    return problems


def _json_call(call: Mapping[str, Any]) -> tuple[str, Any] | None:
    function = call.get("function", call)
    if not isinstance(function, Mapping):
        return None
    name = python_name(function["name"]) if isinstance(function.get("name"), str) else ""
    arguments = function.get("arguments", {})
    if isinstance(arguments, str):
        arguments = parse_json(arguments) if arguments.strip() else {}
    return name, arguments


def _code_call(spec: str, line: str, scope: str) -> tuple[str, dict[str, Any]] | None:
    """`<object>.<tool>(<literals>)` as the tool's name and its arguments by parameter name (an optional parameter
    given None is left out, as the renderer writes an absent one); None for any other code. Read, never run."""
    try:
        node = ast.parse(line.strip(), mode="eval").body
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return None
    tools = {t.name: t for t in _tools_of(spec, scope) or ()}
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in tools):
        return None
    tool = tools[node.func.attr]
    try:
        given = dict(zip(tool.params, (ast.literal_eval(a) for a in node.args), strict=False))
        given |= {k.arg: ast.literal_eval(k.value) for k in node.keywords if k.arg in tool.params}
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
        return None
    if len(node.args) > len(tool.params) or any(k.arg not in tool.params for k in node.keywords):
        return None
    return tool.name, {k: v for k, v in given.items() if v is not None or k in tool.required}


@lru_cache(maxsize=64)
def _schemas_of(_scope: str, spec: str) -> dict[str, Any] | str:
    """The spec's tool schemas, or why they cannot be read; read per scope, as `_tools_of` reads the tools."""
    try:
        return read_schemas(ast.parse(spec))
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        return f"the spec's tool schemas cannot be read: {exc}"
