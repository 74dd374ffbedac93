"""An OpenAI tool-calling agent's messages as the spec `precond convert openai` writes sees them.

One reading for everything that takes such messages: `precond.convert.openai` (logs → spec and programs, and the
service's rendering of a `/check-actions` history and calls) and the embedded guard (`precond_client.guard`),
which keeps the same state in the agent's own process. So a message is accepted, refused (with the same words,
naming the same field) and paired with its call in exactly one way.

The spec: one action (a stub of AGENT) per tool, its parameters in the schema's order; two observations:
`user.says(text)` for a user message and `agent.result(tool, key, ok, value)` for a tool's result, which keeps
the parsed JSON result in `agent.results[tool][key]` (a state-changing tool's in `agent.changes`, errors in
`agent.errors`), `key` being the call's identifying argument (its first `*_id` parameter). A read's result is
also kept, whatever its key, as records in `agent.seen[tool]`: a list result's items (an item that is a list, a
connecting flight's legs, flattened once), the last MAX_SEEN of them, so that a rule can read every search of
the conversation where `results` keeps only the last result per key (a search has none). `AgentState` is that
spec's state kept in Python: the guard updates it message by message where the sandbox runs the program.
Calls and results are paired by position (tool-call ids repeat in real logs). Arguments and results are parsed
JSON, never code. Standard library only: the light client ships it, and the gateway renders histories with it.
"""

from __future__ import annotations

import ast
import json
import math
import unicodedata
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

from precond_client.parsing import parse_module

USER_SPEC = '''from collections import defaultdict
class USER:
  def __init__(self):
    self.messages = 0
    self.last_said = None
  def says(self, text):
    self.messages += 1
    self.last_said = text
'''
MAX_SEEN = 200
"""Records a read tool keeps in `seen` (the oldest dropped first): a conversation's searches, bounded."""
AGENT_STATE = f'''class AGENT:
  def __init__(self, user):
    self.user = user
    self.results = defaultdict(dict)
    self.changes = defaultdict(dict)
    self.errors = defaultdict(dict)
    self.seen = defaultdict(list)
    self.last_ok = None
  def result(self, tool, key, ok, value):
    self.last_ok = ok
    if not ok:
      self.errors[tool][key] = value
    elif tool in WRITES:
      self.changes[tool][key] = value
    else:
      self.results[tool][key] = value
      listed = value if isinstance(value, list) else [value]
      records = [r for v in listed for r in (v if isinstance(v, list) else [v])]
      self.seen[tool][:] = (self.seen[tool] + records)[-{MAX_SEEN}:]
'''
PREAMBLE = ("user = USER()", "agent = AGENT(user)")
RESERVED = {"result", "says", "user", "results", "changes", "errors", "seen", "last_ok"}
"""Names of the spec's own members: a tool cannot be called so."""
RESERVED_PARAMETERS = ("self", "tool", "key", "ok", "value")
WRITE_VERBS = {"book", "cancel", "update", "send", "create", "delete", "modify", "add", "remove", "set", "change",
               "refund", "pay", "exchange", "return", "issue", "transfer_money"}
"""A tool whose name starts with one of these verbs changes state (`book_reservation`); `--writes` overrides."""
SKIPPED_ROLES = {"system", "developer"}
MAX_DEPTH = 32
DOC_CHARS = 200


class ConvertError(Exception):
    """Input of the wrong shape or content: the message names the file and the key (exit 2 in the CLI)."""


class PlaceError(ConvertError):
    """Bad input at a place: `where` names it (a file and key, or a request's field such as `history[3]`)."""

    def __init__(self, where: str, problem: str) -> None:
        super().__init__(f"{where}: {problem}")
        self.where = where


@dataclass(frozen=True)
class Tool:
    name: str
    params: tuple[str, ...]
    """Required parameters in the schema's order, then the optional ones (which default to None)."""
    required: frozenset[str]
    description: str = ""
    schema: dict[str, Any] | None = field(default=None, compare=False, hash=False)
    """Its `parameters` JSON Schema, which a proposed call's arguments must keep (`schemas.tool_schemas`)."""

    @cached_property
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


SCHEMAS = "SCHEMAS"
"""The spec's name for the tools' schemas: a dict literal, tool name -> its `parameters` JSON Schema, which a
proposed call's arguments must keep (`precond_client.schemas.tool_schemas`)."""


def schemas_line(schemas: dict[str, Any]) -> str:
    """The spec's line that holds the schemas (Python literals: `true` is written `True`)."""
    return f"{SCHEMAS} = {schemas!r}"


def read_schemas(tree: ast.Module) -> dict[str, Any]:
    """The schemas a spec holds (`SCHEMAS = {...}`: literals only, nothing run); none when it holds none.
    ValueError when the name is given something else."""
    node = next((n.value for n in tree.body if isinstance(n, ast.Assign)
                 and [getattr(t, "id", None) for t in n.targets] == [SCHEMAS]), None)
    if node is None:
        return {}
    try:
        schemas = ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        raise ValueError(f"`{SCHEMAS}` is not a literal of tool schemas") from None
    if not isinstance(schemas, dict) or not all(isinstance(k, str) and isinstance(v, dict) for k, v in schemas.items()):
        raise ValueError(f"`{SCHEMAS}` is not a dict of tool name -> JSON Schema")
    return schemas


def spec_program(tools: Sequence[Tool], writes: Iterable[str]) -> str:
    lines = [USER_SPEC.rstrip("\n"), f"WRITES = {tuple(sorted(writes))!r}"]
    schemas = {tool.name: tool.schema for tool in tools if tool.schema is not None}
    lines += [schemas_line(schemas)] if schemas else []
    lines.append(AGENT_STATE.rstrip("\n"))
    for tool in tools:
        params = [p for p in tool.params if p in tool.required] + [f"{p}=None" for p in tool.params
                                                                   if p not in tool.required]
        doc = " ".join(tool.description.split())
        doc = doc if len(doc) <= DOC_CHARS else doc[: DOC_CHARS - 3] + "..."
        lines.append(f"  def {tool.name}({', '.join(['self', *params])}):")
        lines.append(f"    {doc!r}" if doc else "    pass")
    return "\n".join(lines) + "\n"


def converter_spec(spec: str) -> tuple[tuple[Tool, ...], frozenset[str]]:
    """The tools and state-changing tools of a spec `precond convert openai` wrote, character for character (the
    spec written again from what is read must be the text given); ValueError says where it is not. What such a
    spec does is `AgentState`: nothing of the text is run."""
    try:
        tree = parse_module(spec)
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        raise ValueError(f"not Python: {exc}") from None
    writes = next((node.value for node in tree.body if isinstance(node, ast.Assign)
                   and [getattr(t, "id", None) for t in node.targets] == ["WRITES"]), None)
    agent = next((node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "AGENT"), None)
    if writes is None or agent is None:
        raise ValueError("no `WRITES = (...)` and `class AGENT`: not a spec `precond convert openai` writes")
    try:
        names = ast.literal_eval(writes)
    except ValueError:
        raise ValueError("`WRITES` is not a tuple of tool names") from None
    schemas = read_schemas(tree)
    tools = tuple(replace(tool, schema=schemas.get(tool.name)) for tool in (
        _stub_tool(node) for node in agent.body if isinstance(node, ast.FunctionDef)
        and node.name not in ("__init__", "result")))
    if not isinstance(names, tuple) or not all(isinstance(n, str) for n in names):
        raise ValueError("`WRITES` is not a tuple of tool names")
    written = spec_program(tools, names)
    if written != spec:
        given, wanted = spec.splitlines(), written.splitlines()
        at = next((n for n, (a, b) in enumerate(zip(given, wanted, strict=False)) if a != b),
                  min(len(given), len(wanted)))
        raise ValueError(f"line {at + 1} differs from what `precond convert openai` writes: it is not that spec "
                         "(one an older version wrote: convert the logs again; a rule over another spec needs the "
                         "service)")
    return tools, frozenset(names)


def _stub_tool(node: ast.FunctionDef) -> Tool:
    params = tuple(a.arg for a in node.args.args[1:])
    required = frozenset(params[: len(params) - len(node.args.defaults)])
    first = node.body[0] if node.body else None
    doc = first.value.value if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) else ""
    return Tool(node.name, params, required, doc if isinstance(doc, str) else "")


def check_json(value: Any, where: str) -> None:
    """That a value is JSON (finite numbers, bounded nesting, string keys)."""
    problem = None if type(value) in SCALARS else json_problem(value)
    if problem is not None:
        raise PlaceError(where, problem)


SCALARS = frozenset({str, int, bool, type(None)})


def json_problem(value: Any, depth: int = 0) -> str | None:
    """Why a value is not JSON (depth first, in order: the first problem), or None. Values of the plain scalar
    types are passed over without a call: a tool's result holds thousands."""
    if depth > MAX_DEPTH:
        return f"nested deeper than {MAX_DEPTH} levels"
    if isinstance(value, float):
        return None if math.isfinite(value) else "only finite numbers are allowed"
    inner = depth + 1 <= MAX_DEPTH
    if isinstance(value, list):
        for item in value:
            if not (inner and type(item) in SCALARS) and (problem := json_problem(item, depth + 1)) is not None:
                return problem
        return None
    if isinstance(value, dict):
        for name, item in value.items():
            if not isinstance(name, str):
                return f"a key {name!r} is not a string"
            if not (inner and type(item) in SCALARS) and (problem := json_problem(item, depth + 1)) is not None:
                return problem
        return None
    if value is None or isinstance(value, str | bool | int):
        return None
    return f"{type(value).__name__} is not a JSON value"


def literal(value: Any, where: str) -> str:
    """`repr` of a JSON value, after checking it is one (finite numbers, bounded nesting)."""
    check_json(value, where)
    return repr(value)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


_DECODER = json.JSONDecoder(parse_constant=_no_constant)


def parse_json(text: str) -> Any:
    """JSON with NaN/Infinity refused; raises ValueError (or RecursionError) on anything else. `json.loads` with
    one decoder made once (it makes one a call when given a hook)."""
    if text.startswith("\ufeff"):
        raise json.JSONDecodeError("Unexpected UTF-8 BOM (decode using utf-8-sig)", text, 0)
    return _DECODER.decode(text)


def _text(content: Any, where: str) -> str | None:
    if content is None or isinstance(content, str):
        return content
    if isinstance(content, list) and all(isinstance(p, dict) and isinstance(p.get("text"), str) for p in content):
        return "".join(p["text"] for p in content)
    raise PlaceError(where, "content must be a string, null or a list of {'type': 'text', 'text'} parts")


def outcome(content: str) -> tuple[bool, Any]:
    """(success, value): text starting with 'Error' is a failure kept as text; otherwise parsed JSON, or the text
    when it is not JSON."""
    if content.lstrip().lower().startswith("error"):
        return False, content
    try:
        return True, parse_json(content)
    except (ValueError, RecursionError):
        return True, content


def _key(value: Any) -> Any:
    """The identifying argument as a dictionary key: a scalar as is, anything else as its JSON text."""
    if value is None or isinstance(value, str | int | bool) or (isinstance(value, float) and math.isfinite(value)):
        return value
    return json.dumps(value, sort_keys=True)


def python_name(name: str) -> str:
    """The identifier Python binds for `name` (NFKC, PEP 3131: `ｌｏｏｋｕｐ` is `lookup`): a tool, its
    parameters and a result's tool are matched in that form, as the spec's own names are read
    (`precond.programs.names`, which this standalone module cannot import)."""
    return unicodedata.normalize("NFKC", name)


def call_line(call: Call, tool: Tool) -> str:
    """`agent.tool(args...)`: every parameter by position, literals only (the arguments were checked)."""
    return f"agent.{tool.name}({', '.join(repr(call.arguments.get(p)) for p in tool.params)})"


class Reader:
    """Reads one trajectory's messages in order: checks each, pairs results with calls by position, and hands
    what happened to `said`, `called` and `answered`, which a subclass turns into program lines or state."""

    def __init__(self, tools: Sequence[Tool] | dict[str, Tool], where: str) -> None:
        self.tools = tools if isinstance(tools, dict) else {t.name: t for t in tools}
        self.where = where
        self.statements = len(PREAMBLE)
        """Program lines so far: the line a call is on."""
        self.pending: deque[Call] = deque()

    def said(self, text: str | None) -> None:
        raise NotImplementedError

    def called(self, call: Call) -> None:
        raise NotImplementedError

    def answered(self, call: Call) -> None:
        raise NotImplementedError

    def message(self, index: int, message: Any) -> None:
        at = f"{self.where}[{index}]"
        if not isinstance(message, dict) or not isinstance(message.get("role"), str):
            raise PlaceError(at, "not an OpenAI chat message (an object with a 'role')")
        role = message["role"]
        if role == "user":
            self.said(_text(message.get("content"), f"{at}.content"))
            self.statements += 1
        elif role == "assistant":
            _text(message.get("content"), f"{at}.content")
            calls = message.get("tool_calls") or []
            if not isinstance(calls, list):
                raise PlaceError(f"{at}.tool_calls", "must be a list")
            for n, call in enumerate(calls):
                self.call(call, f"{at}.tool_calls[{n}]")
        elif role in ("tool", "function"):
            self.result(message, at)
        elif role not in SKIPPED_ROLES:
            raise PlaceError(f"{at}.role", f"{role!r} is not an OpenAI role (system, user, assistant, tool)")

    def read_call(self, call: Any, at: str) -> tuple[Call, Tool]:
        """A proposed `{name, arguments}` (or `{function: {...}}`) checked against its tool's parameters."""
        function = call.get("function", call) if isinstance(call, dict) else None
        if not isinstance(function, dict):
            raise PlaceError(at, "expected {'function': {'name', 'arguments'}}")
        at = f"{at}.function" if "function" in call else at
        name = function.get("name")
        tool = self.tools.get(python_name(name)) if isinstance(name, str) else None
        if tool is None:
            known = ", ".join(sorted(self.tools)[:20])
            raise PlaceError(f"{at}.name", f"no tool {name!r} in the tools ({known})")
        arguments = self.arguments(tool, function.get("arguments", {}), f"{at}.arguments")
        for p in tool.params:
            value = arguments.get(p)
            problem = None if type(value) in SCALARS else json_problem(value)
            if problem is not None:
                raise PlaceError(f"{at}.arguments.{p}", problem)
        key = _key(arguments.get(tool.key)) if tool.key else None
        return Call(tool.name, arguments, self.statements, key), tool

    def call(self, call: Any, at: str) -> Call:
        made, _ = self.read_call(call, at)
        self.called(made)
        self.statements += 1
        self.pending.append(made)
        return made

    @staticmethod
    def arguments(tool: Tool, raw: Any, at: str) -> dict[str, Any]:
        if isinstance(raw, str):
            try:
                raw = parse_json(raw) if raw.strip() else {}
            except (ValueError, RecursionError) as exc:
                raise PlaceError(at, f"not valid JSON: {exc}") from None
        if not isinstance(raw, dict):
            raise PlaceError(at, f"must be a JSON object, found {type(raw).__name__}")
        named: dict[str, Any] = {python_name(k): v for k, v in raw.items()}  # as the spec's parameters are named
        if len(named) < len(raw):
            raise PlaceError(at, "names one parameter twice (two spellings of one name)")
        unknown = [k for k in named if k not in tool.params]
        if unknown:
            raise PlaceError(at, f"{tool.name} has no parameter {unknown[0]!r} ({', '.join(tool.params) or 'none'})")
        missing = [p for p in tool.params if p in tool.required and p not in named]
        if missing:
            raise PlaceError(at, f"missing required argument {missing[0]!r} of {tool.name}")
        return named

    def result(self, message: dict[str, Any], at: str) -> None:
        if not self.pending:
            raise PlaceError(at, "a tool result that pairs with no call (every earlier call already has its result)")
        pending = self.pending[0]
        name = message.get("name")
        if name is not None and (not isinstance(name, str) or python_name(name) != pending.tool):
            raise PlaceError(f"{at}.name", f"result of {name!r} pairs by position with a call of {pending.tool!r}")
        content = _text(message.get("content"), f"{at}.content") or ""
        ok, value = outcome(content)
        check_json(value, f"{at}.content")
        self.pending.popleft()
        pending.result = (ok, value)
        self.answered(pending)
        self.statements += 1


@dataclass
class UserState:
    """USER of the spec: what its `says` keeps."""

    messages: int = 0
    last_said: str | None = None


@dataclass
class AgentState:
    """AGENT of the spec after the history: the state its rules read. Its tables are plain dictionaries where the
    spec has `defaultdict(dict)`: a rule that reads a table with a key it lacks sees the empty dictionary the
    spec's would insert, on its own copy (`precond_client.rule_interpreter`)."""

    writes: frozenset[str]
    user: UserState = field(default_factory=UserState)
    results: dict[str, dict[Any, Any]] = field(default_factory=dict)
    changes: dict[str, dict[Any, Any]] = field(default_factory=dict)
    errors: dict[str, dict[Any, Any]] = field(default_factory=dict)
    seen: dict[str, list[Any]] = field(default_factory=dict)
    last_ok: bool | None = None

    def result(self, tool: str, key: Any, ok: bool, value: Any) -> None:
        """AGENT.result of the spec (AGENT_STATE)."""
        self.last_ok = ok
        if not ok:
            self.errors.setdefault(tool, {})[key] = value
        elif tool in self.writes:
            self.changes.setdefault(tool, {})[key] = value
        else:
            self.results.setdefault(tool, {})[key] = value
            self.seen[tool] = (self.seen.get(tool, []) + records(value))[-MAX_SEEN:]


def records(value: Any) -> list[Any]:
    """A read's result as the records `seen` keeps (AGENT_STATE): a list's items, an item that is a list flattened
    once (a one-stop search's pairs of legs); anything else is one record."""
    return [r for v in (value if isinstance(value, list) else [value]) for r in (v if isinstance(v, list) else [v])]


class StateReader(Reader):
    """Messages into `AgentState`, one at a time: the program's effect without the program."""

    def __init__(self, tools: Sequence[Tool] | dict[str, Tool], writes: frozenset[str], where: str) -> None:
        super().__init__(tools, where)
        self.state = AgentState(writes)

    def said(self, text: str | None) -> None:
        self.state.user.messages += 1
        self.state.user.last_said = text

    def called(self, call: Call) -> None:
        """A stub: the call itself changes nothing."""

    def answered(self, call: Call) -> None:
        ok, value = call.result or (False, None)
        self.state.result(call.tool, call.key, ok, value)
