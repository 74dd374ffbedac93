"""OpenAI chat logs of a tool-calling agent → spec, demonstration programs (docs/converting.md).

The spec is derived from the tools' JSON schemas: one action (a stub of AGENT) per tool, its parameters in
the schema's order; two observations: `user.says(text)` for a user message and `agent.result(tool, key, ok,
value)` for a tool's result, which keeps the parsed JSON result in `agent.results[tool][key]` (errors in
`agent.errors`), `key` being the call's identifying argument (its first `*_id` parameter), so that a rule can
say "a successful read of *this* reservation came before this write". Calls and results are paired by position
(tool-call ids repeat in real logs). Arguments and results are JSON parsed here and written with `repr` as
literals: nothing in a log can become code. Standard library only: the gateway renders histories with it.
"""

from __future__ import annotations

import json
import keyword
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from precond.convert.shape import ConvertError
from precond.programs import checks
from precond.programs.history import render as render_events

USER_SPEC = '''from collections import defaultdict
class USER:
  def __init__(self):
    self.messages = 0
    self.last_said = None
  def says(self, text):
    self.messages += 1
    self.last_said = text
'''
AGENT_STATE = '''class AGENT:
  def __init__(self, user):
    self.user = user
    self.results = defaultdict(dict)
    self.changes = defaultdict(dict)
    self.errors = defaultdict(dict)
    self.last_ok = None
  def result(self, tool, key, ok, value):
    self.last_ok = ok
    if not ok:
      self.errors[tool][key] = value
    elif tool in WRITES:
      self.changes[tool][key] = value
    else:
      self.results[tool][key] = value
'''
PREAMBLE = ("user = USER()", "agent = AGENT(user)")
RESERVED = {"result", "says", "user", "results", "changes", "errors", "last_ok"}
"""Names of the spec's own members: a tool cannot be called so."""
WRITE_VERBS = {"book", "cancel", "update", "send", "create", "delete", "modify", "add", "remove", "set", "change",
               "refund", "pay", "exchange", "return", "issue", "transfer_money"}
"""A tool whose name starts with one of these verbs changes state (`book_reservation`); `--writes` overrides."""
SKIPPED_ROLES = {"system", "developer"}
MAX_DEPTH = 32
DOC_CHARS = 200


@dataclass(frozen=True)
class Tool:
    name: str
    params: tuple[str, ...]
    """Required parameters in the schema's order, then the optional ones (which default to None)."""
    required: frozenset[str]
    description: str = ""

    @property
    def key(self) -> str | None:
        """The identifying argument: the first parameter named `id` or `*_id` (None: results keyed None)."""
        return next((p for p in self.params if p == "id" or p.endswith("_id")), None)


def writes_of(tools: Iterable[Tool]) -> set[str]:
    return {t.name for t in tools if t.name.split("_")[0] in WRITE_VERBS or t.name in WRITE_VERBS}


@dataclass
class Call:
    """A tool call as the log has it: what the evaluation labels and the guard judges."""

    tool: str
    arguments: dict[str, Any]
    line: int
    """Its line in the program (0-based): the lines before it are the history it is judged after."""
    key: Any = None
    result: tuple[bool, Any] | None = None
    """(success, parsed value), once its result has come."""


@dataclass
class Trajectory:
    name: str
    program: str
    calls: list[Call] = field(default_factory=list)
    reward: float | None = None


@dataclass
class Converted:
    spec: str
    tools: list[Tool]
    writes: set[str]
    trajectories: list[Trajectory] = field(default_factory=list)

    @property
    def without_writes(self) -> int:
        """Trajectories with no state-changing call: accepted and counted, never dropped silently."""
        return sum(1 for t in self.trajectories if not any(c.tool in self.writes for c in t.calls))


class PlaceError(ConvertError):
    """Bad input at a place: `where` names it (a file and key, or a request's field such as `history[3]`)."""

    def __init__(self, where: str, problem: str) -> None:
        super().__init__(f"{where}: {problem}")
        self.where = where


def _fail(where: str, message: str) -> PlaceError:
    return PlaceError(where, message)


def _identifier(name: object, where: str, what: str) -> str:
    if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name) or name.startswith("_"):
        raise _fail(where, f"{what} {name!r} cannot be a Python name (letters, digits, _; not a keyword)")
    return name


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
        for param in properties:
            _identifier(param, f"{where}.function.parameters.properties", "parameter")
            if param in ("self", "tool", "key", "ok", "value"):
                raise _fail(f"{where}.function.parameters.properties", f"parameter {param!r} is reserved")
        unknown = [r for r in required if r not in properties]
        if unknown:
            raise _fail(f"{where}.function.parameters.required", f"{unknown[0]!r} is not among its properties")
        ordered = [p for p in properties if p in required] + [p for p in properties if p not in required]
        description = function.get("description")
        tools[name] = Tool(name, tuple(ordered), frozenset(required),
                           description if isinstance(description, str) else "")
    return list(tools.values())


def spec_program(tools: Sequence[Tool], writes: Iterable[str]) -> str:
    lines = [USER_SPEC.rstrip("\n"), f"WRITES = {tuple(sorted(writes))!r}", AGENT_STATE.rstrip("\n")]
    for tool in tools:
        params = [p for p in tool.params if p in tool.required] + [f"{p}=None" for p in tool.params
                                                                   if p not in tool.required]
        doc = " ".join(tool.description.split())
        doc = doc if len(doc) <= DOC_CHARS else doc[: DOC_CHARS - 3] + "..."
        lines.append(f"  def {tool.name}({', '.join(['self', *params])}):")
        lines.append(f"    {doc!r}" if doc else "    pass")
    return "\n".join(lines) + "\n"


def literal(value: Any, where: str) -> str:
    """`repr` of a JSON value, after checking it is one (finite numbers, bounded nesting)."""
    _check_json(value, where, 0)
    return repr(value)


def _check_json(value: Any, where: str, depth: int) -> None:
    if depth > MAX_DEPTH:
        raise _fail(where, f"nested deeper than {MAX_DEPTH} levels")
    if isinstance(value, float) and not math.isfinite(value):
        raise _fail(where, "only finite numbers are allowed")
    if isinstance(value, list):
        for item in value:
            _check_json(item, where, depth + 1)
    elif isinstance(value, dict):
        for name, item in value.items():
            if not isinstance(name, str):
                raise _fail(where, f"a key {name!r} is not a string")
            _check_json(item, where, depth + 1)
    elif not (value is None or isinstance(value, str | bool | int | float)):
        raise _fail(where, f"{type(value).__name__} is not a JSON value")


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


def parse_json(text: str) -> Any:
    """JSON with NaN/Infinity refused; raises ValueError (or RecursionError) on anything else."""
    return json.loads(text, parse_constant=_no_constant)


def _text(content: Any, where: str) -> str | None:
    if content is None or isinstance(content, str):
        return content
    if isinstance(content, list) and all(isinstance(p, dict) and isinstance(p.get("text"), str) for p in content):
        return "".join(p["text"] for p in content)
    raise _fail(where, "content must be a string, null or a list of {'type': 'text', 'text'} parts")


class Renderer:
    """One trajectory's messages → program lines, calls paired with results by position."""

    def __init__(self, tools: Sequence[Tool], where: str) -> None:
        self.tools = {t.name: t for t in tools}
        self.where = where
        self.lines: list[str] = list(PREAMBLE)
        self.calls: list[Call] = []
        self.pending: list[Call] = []

    def message(self, index: int, message: Any) -> None:
        at = f"{self.where}[{index}]"
        if not isinstance(message, dict) or not isinstance(message.get("role"), str):
            raise _fail(at, "not an OpenAI chat message (an object with a 'role')")
        role = message["role"]
        if role == "user":
            text = _text(message.get("content"), f"{at}.content")
            self.lines.append(f"user.says({text!r})")
        elif role == "assistant":
            _text(message.get("content"), f"{at}.content")
            calls = message.get("tool_calls") or []
            if not isinstance(calls, list):
                raise _fail(f"{at}.tool_calls", "must be a list")
            for n, call in enumerate(calls):
                self.call(call, f"{at}.tool_calls[{n}]")
        elif role in ("tool", "function"):
            self.result(message, at)
        elif role not in SKIPPED_ROLES:
            raise _fail(f"{at}.role", f"{role!r} is not an OpenAI role (system, user, assistant, tool)")

    def call(self, call: Any, at: str) -> str:
        """A call as `agent.tool(args...)`; also what the gateway makes of a proposed `{name, arguments}`."""
        function = call.get("function", call) if isinstance(call, dict) else None
        if not isinstance(function, dict):
            raise _fail(at, "expected {'function': {'name', 'arguments'}}")
        at = f"{at}.function" if "function" in call else at
        name = function.get("name")
        tool = self.tools.get(name) if isinstance(name, str) else None
        if tool is None:
            known = ", ".join(sorted(self.tools)[:20])
            raise _fail(f"{at}.name", f"no tool {name!r} in the tools ({known})")
        arguments = self.arguments(tool, function.get("arguments", {}), f"{at}.arguments")
        rendered = ", ".join(literal(arguments.get(p), f"{at}.arguments.{p}") for p in tool.params)
        line = f"agent.{tool.name}({rendered})"
        made = Call(tool.name, arguments, len(self.lines), _key(arguments.get(tool.key)) if tool.key else None)
        self.lines.append(line)
        self.calls.append(made)
        self.pending.append(made)
        return line

    @staticmethod
    def arguments(tool: Tool, raw: Any, at: str) -> dict[str, Any]:
        if isinstance(raw, str):
            try:
                raw = parse_json(raw) if raw.strip() else {}
            except (ValueError, RecursionError) as exc:
                raise _fail(at, f"not valid JSON: {exc}") from None
        if not isinstance(raw, dict):
            raise _fail(at, f"must be a JSON object, found {type(raw).__name__}")
        unknown = [k for k in raw if k not in tool.params]
        if unknown:
            raise _fail(at, f"{tool.name} has no parameter {unknown[0]!r} ({', '.join(tool.params) or 'none'})")
        missing = [p for p in tool.params if p in tool.required and p not in raw]
        if missing:
            raise _fail(at, f"missing required argument {missing[0]!r} of {tool.name}")
        return raw

    def result(self, message: dict[str, Any], at: str) -> None:
        if not self.pending:
            raise _fail(at, "a tool result that pairs with no call (every earlier call already has its result)")
        pending = self.pending.pop(0)
        name = message.get("name")
        if name is not None and name != pending.tool:
            raise _fail(f"{at}.name", f"result of {name!r} pairs by position with a call of {pending.tool!r}")
        content = _text(message.get("content"), f"{at}.content") or ""
        ok, value = outcome(content)
        rendered = literal(value, f"{at}.content")
        pending.result = (ok, value)
        self.lines.append(f"agent.result({pending.tool!r}, {pending.key!r}, {ok}, {rendered})")

    def program(self) -> str:
        return "\n".join(self.lines) + "\n"


def _key(value: Any) -> Any:
    """The identifying argument as a dictionary key: a scalar as is, anything else as its JSON text."""
    if value is None or isinstance(value, str | int | bool) or (isinstance(value, float) and math.isfinite(value)):
        return value
    return json.dumps(value, sort_keys=True)


def outcome(content: str) -> tuple[bool, Any]:
    """(success, value): text starting with 'Error' is a failure kept as text; otherwise parsed JSON, or the text
    when it is not JSON."""
    if content.lstrip().lower().startswith("error"):
        return False, content
    try:
        return True, parse_json(content)
    except (ValueError, RecursionError):
        return True, content


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
            reward = item.get("reward")
            runs.append((name, item["traj"], f"{source}: [{n}].traj",
                         float(reward) if isinstance(reward, int | float) else None))
        else:
            raise _fail(f"{source}: [{n}]", "expected a list of messages or a {'traj': [...]} record")
    return runs


def _record_name(record: dict[str, Any], index: int) -> str:
    task, trial = record.get("task_id"), record.get("trial")
    if isinstance(task, int | str) and isinstance(trial, int | str):
        return f"task{task}-trial{trial}"
    return str(index)


def convert(data: Any, tools_data: Any, source: str = "trajectories", tools_source: str = "tools",
            writes: set[str] | None = None) -> Converted:
    """Parsed trajectories and tool schemas → the spec and one program per trajectory."""
    tools = read_tools(tools_data, tools_source)
    chosen = writes_of(tools) if writes is None else writes
    unknown = sorted(chosen - {t.name for t in tools})
    if unknown:
        raise _fail(tools_source, f"state-changing tool {unknown[0]!r} is not among the tools")
    converted = Converted(spec_program(tools, chosen), tools, chosen)
    for name, messages, where, reward in _runs(data, source):
        renderer = render(messages, tools, where)
        converted.trajectories.append(Trajectory(name, renderer.program(), renderer.calls, reward))
    return converted


# ---- inside the API: histories and calls of a check or next-action request ---------------------------------

def spec_tools(spec: str, field: str) -> tuple[Tool, ...]:
    """The tools of a spec `precond convert openai` wrote: AGENT's stubs, their parameters as declared."""
    tools = _tools_of(spec)
    if tools is None:
        raise _fail(field, "OpenAI messages and tool calls need a spec made by `precond convert openai` (class AGENT "
                    "with result(tool, key, ok, value), class USER with says(text))")
    return tools


def _tools_of(spec: str) -> tuple[Tool, ...] | None:
    """Parsed per request, never cached across requests: a cache shared by the gateway's tenants would let one
    tell, by the time its own check takes, that another sent the same spec (docs/security.md)."""
    _, methods = checks.spec_methods(spec)
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
        return render(list(history), spec_tools(spec, field), field).program()
    except PlaceError as exc:
        raise _problem(exc) from None


def call_lines(spec: str, calls: Sequence[str | Mapping[str, Any]], field: str = "calls") -> list[str]:
    """Proposed calls as program lines: code as sent, tool calls `{name, arguments}` rendered with literals."""
    if all(isinstance(c, str) for c in calls):
        return [c for c in calls if isinstance(c, str)]
    try:
        renderer = Renderer(spec_tools(spec, field), field)
        return [c if isinstance(c, str) else renderer.call(dict(c), f"{field}[{n}]") for n, c in enumerate(calls)]
    except PlaceError as exc:
        raise _problem(exc) from None
