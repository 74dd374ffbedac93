"""Static reading of a user's program spec: which methods are actions, and the text the prompts are made of.

Only `ast` is used here: the spec is untrusted, so it is parsed (never executed) in the worker; everything
that runs it goes through the sandbox. What a method, an action and a stub are is `programs.read_methods`'s
answer, the one the sandbox and the evaluation use too. Parsing errors become `InvalidProgram` with the
line, so the gateway can answer 422 before any model time is spent.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from precond.programs import Method, checks, main_body
from precond_client.schemas.errors import InvalidInput, InvalidProgram, UnknownAction


@dataclass(frozen=True)
class Spec:
    source: str
    tree: ast.Module
    methods: dict[str, Method]

    @property
    def stub_actions(self) -> list[str]:
        return [name for name, method in self.methods.items() if method.stub]


def as_error(exc: checks.ProgramProblem) -> InvalidInput:
    """The API error of a static check's problem (the gateway answers the same one before queueing)."""
    problem = exc.problem
    cls = {checks.INVALID_PROGRAM: InvalidProgram, checks.UNKNOWN_ACTION: UnknownAction}.get(problem.type, InvalidInput)
    return cls(problem.message, field=problem.field)


def parse_source(source: str, field: str) -> ast.Module:
    """Parse untrusted source, turning every failure (syntax, nesting too deep, NUL bytes) into a 422."""
    try:
        return checks.parse(source, field)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def parse_spec(source: str) -> Spec:
    try:
        tree, methods = checks.spec_methods(source)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc
    return Spec(source, tree, methods)


def remembered_spec(scope: str, source: str) -> Spec:
    """`parse_spec`, its reading remembered per scope (`checks.remembered_spec_methods`): a tenant's guard sends
    the same spec with every check."""
    try:
        tree, methods = checks.remembered_spec_methods(scope, source)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc
    return Spec(source, tree, methods)


def resolve_actions(spec: Spec, requested: Sequence[str] | None) -> list[str]:
    """Requested names must exist (an unknown one gets the closest known name); by default every stub
    method is an action."""
    try:
        return checks.resolve_actions(spec.methods, requested)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def check_preconditions(spec: Spec, preconditions: dict[str, list[str]], scope: str | None = None) -> None:
    """Known action names (else the closest), and each rule one expression (`assert x` says to drop it);
    with `scope`, a success is remembered for that scope (`checks.remembered_check_preconditions`)."""
    try:
        if scope is None:
            checks.check_preconditions(spec.methods, preconditions)
        else:
            checks.remembered_check_preconditions(scope, spec.source, spec.methods, preconditions)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def check_calls(spec: Spec, preconditions: dict[str, list[str]], history: str, calls: list[str], scope: str) -> None:
    """Proposed calls of the agent's actions only (`checks.check_calls`): the gateway's 422, the same here. The
    history must parse; what it binds is remembered per `scope` (`checks.history_receivers`)."""
    try:
        receivers = checks.history_receivers(scope, checks.spec_classes(spec.methods), history)
        checks.check_calls(spec.methods, preconditions, receivers, calls)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def call_actions(spec: Spec, history: str, calls: Sequence[str], scope: str) -> list[str | None]:
    """The action each proposed call calls (`checks.called_action`), read as `check_calls` reads it."""
    receivers = checks.history_receivers(scope, checks.spec_classes(spec.methods), history)
    return [checks.called_action(spec.methods, receivers, call) for call in calls]


def observation_source(spec: Spec, actions: Iterable[str]) -> str:
    """The spec without the action methods: the paper's observation function definitions F_O.

    Action stubs are left out so the model is not primed with `pass` bodies next to the `assert` it completes.
    """
    excluded = {spec.methods[a].node for a in actions}
    lines = spec.source.splitlines()
    drop: set[int] = set()
    for node in excluded:
        start = node.decorator_list[0].lineno if node.decorator_list else node.lineno
        drop.update(range(start - 1, (node.end_lineno or node.lineno)))
    return "\n".join(line for i, line in enumerate(lines) if i not in drop).rstrip() + "\n"


def action_header(spec: Spec, action: str) -> str:
    """`class C:` context line plus `def a(self, ...):` and the `assert` keyword, as the paper prompts.

    The spec's own indentation unit is kept, so the model continues the style it has just read.
    """
    method = spec.methods[action]
    return f"class {method.cls}:\n{_definition(spec, action)}\n{_indent(spec, action) * 2}assert"


def asserted(spec: Spec, action: str, rules: Sequence[str]) -> str:
    """The action's definition with `rules` as its body, indented like `action_header`."""
    body = "".join(f"\n{_indent(spec, action) * 2}assert {rule}" for rule in rules)
    return _definition(spec, action) + body


def _definition(spec: Spec, action: str) -> str:
    method = spec.methods[action]
    return f"{_indent(spec, action)}def {method.name}({', '.join(('self', *method.signature))}):"


def _indent(spec: Spec, action: str) -> str:
    return " " * (spec.methods[action].node.col_offset or 4)


def render_program(spec: Spec, preconditions: dict[str, list[str]]) -> str:
    """The spec with each action's assertions written into its body, replacing a stub body."""
    lines = spec.source.splitlines()
    edits: list[tuple[int, int, list[str]]] = []
    for action, assertions in preconditions.items():
        if not assertions or action not in spec.methods:
            continue
        node = spec.methods[action].node
        indent = " " * (node.col_offset + (node.col_offset or 4))
        body = [f"{indent}assert {a}" for a in assertions]
        first, last = node.body[0], node.body[-1]
        stub = spec.methods[action].stub
        if first.lineno == node.lineno:  # one-line `def f(self): ...`: split header and body
            header = lines[node.lineno - 1]
            cut = header.index(":", header.index(")")) + 1
            rest = [] if stub else [indent + header[cut:].strip()]
            edits.append((node.lineno - 1, node.lineno, [header[:cut], *body, *rest]))
        elif stub:
            edits.append((first.lineno - 1, last.end_lineno or last.lineno, body))
        else:
            edits.append((first.lineno - 1, first.lineno - 1, body))
    for start, end, new in sorted(edits, reverse=True):
        lines[start:end] = new
    return "\n".join(lines) + "\n"


def skip_statements(source: str, positions: Iterable[int]) -> str:
    """The program with the main-body statements at `positions` replaced by `pass`, every line number kept.

    Used to verify kept rules on the demonstrations minus the calls they refuse by design. A statement that
    shares its last line with another one is left as it is (verification then judges it as written).
    """
    wanted = set(positions)
    if not wanted:
        return source
    body = main_body(ast.parse(source))
    lines = source.splitlines()
    for position in sorted(wanted):
        if not 0 <= position < len(body):
            continue
        stmt = body[position]
        first, last = stmt.lineno - 1, (stmt.end_lineno or stmt.lineno) - 1
        head, tail = lines[first].encode(), lines[last].encode()
        end = stmt.end_col_offset if stmt.end_col_offset is not None else len(tail)
        if tail[end:].strip() and last != first:
            continue
        rest = tail[end:] if last == first else b""
        lines[first] = (head[: stmt.col_offset] + b"pass" + rest).decode()
        for k in range(first + 1, last + 1):
            lines[k] = ""
    return "\n".join(lines) + ("\n" if source.endswith("\n") else "")
