"""Guard an agent's tool calls where it runs: in its own process (`Guard`), or through the service
(`ServiceGuard`). Both judge a call given the agent's OpenAI chat messages so far and answer the service's
`CallVerdict`; the adapters (`precond_client.adapters`) put them in front of an agent framework's tools.

`Guard` is built from a stored set (or a spec and rules) whose spec is the one `precond convert openai` writes:
then nothing in the set is code to run. The state that spec's program would build is kept message by message
(`openai_log.StateReader`: the converter's own reading, so a message is refused with the words and field of the
service's 422), and each rule is evaluated by `rule_interpreter`, which evaluates exactly the forms the learner
writes; a set with any other rule, or another spec, is not embeddable (`NotEmbeddable`, naming the rule and
why): `ServiceGuard` judges it. Verdicts are the service's, violations, error texts and `decided` labels
included, and so is where a history already broke a rule (`Session.history_violation`, `Guard.check_actions`;
tests/client/test_guard_differential.py compares them on real logs).

A call the guard cannot judge (arguments the converter refuses, a history it could not read; for
`ServiceGuard`, also a service that does not answer) is refused with the reason, or, with
`fail_closed=False`, allowed with the reason in `error`. A tool the set does not have is always refused.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from precond_client.errors import InvalidInput, PrecondError
from precond_client.openai_log import (
    Call,
    PlaceError,
    StateReader,
    Tool,
    call_line,
    converter_spec,
    parse_json,
)
from precond_client.rule_interpreter import (
    LISTS,
    TABLE,
    VALUE,
    Evaluate,
    Frame,
    OutsideGrammar,
    Scope,
    Shape,
    compile_rule,
)
from precond_client.schemas import CallVerdict, CheckResponse, PreconditionSet, RuleStatus, rule_status
from precond_client.schemas.tool_schemas import SCHEMA_BROKEN, schema_problem

AGENT_SHAPE = Shape("object", {
    "user": Shape("object", {"messages": VALUE, "last_said": VALUE}),
    "results": TABLE, "changes": TABLE, "errors": TABLE, "seen": LISTS, "last_ok": VALUE,
})
"""What a rule may read of the state: the attributes `AGENT_STATE` and `USER_SPEC` give AGENT and USER."""
MAX_CALL_CHARS = 4000
"""The sandbox refuses a proposed call longer than this unread (`precond.sandbox.astfilter.MAX_EXPRESSION_CHARS`)."""
TOO_LONG = "rejected: not a single-line call"
MESSAGE_CHARS = 500
RULE_CHARS = 200
VIOLATION_CHARS = 4000
NO_SUCH_TOOL = "no such tool in the set"


class NotEmbeddable(ValueError):
    """A set the embedded guard cannot judge: each of `problems` names a rule (or the spec) and why; the
    service judges it (`ServiceGuard`)."""

    def __init__(self, problems: Sequence[str]) -> None:
        super().__init__("not embeddable: " + "; ".join(problems))
        self.problems = list(problems)


def clean(text: str, limit: int = MESSAGE_CHARS) -> str:
    """Text as the sandbox reports it (`precond.sandbox.child.values.clean`): no lone surrogates, bounded."""
    safe = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return safe if len(safe) <= limit else safe[: limit - 3] + "..."


def _tupled(value: Any) -> Any:
    """JSON arrays as tuples, the form the sandbox gives a proposed call's argument values."""
    if isinstance(value, list):
        return tuple(_tupled(v) for v in value)
    return value


@dataclass(frozen=True)
class _Rule:
    text: str
    evaluate: Evaluate


def _verdict(call: str, allowed: bool, violations: list[str] | None = None, decided: dict[str, str] | None = None,
             error: str | None = None, status: tuple[str, RuleStatus] | None = None) -> CallVerdict:
    """`status`: the action judged and what its rule rests on (`schemas.rule_status`), as the service says."""
    # model_construct: every field is already of its type; validation would be most of a check's time
    action, rule_status = status if status is not None else (None, None)
    return CallVerdict.model_construct(call=call, allowed=allowed, violations=violations or [],
                                       decided=decided or {}, error=error, action=action, rule_status=rule_status)


class GuardSession(Protocol):
    """One conversation: its messages, added as they come, and the calls judged after them."""

    def add(self, message: Mapping[str, Any]) -> None: ...

    def check(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict: ...

    async def acheck(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict: ...


class Judge(Protocol):
    """What the adapters take: `Guard` or `ServiceGuard`."""

    fail_closed: bool

    @property
    def name(self) -> str: ...

    def session(self) -> GuardSession: ...


class Guard:
    """The embedded guard of one set. Immutable: share it across conversations; each has its `session()`."""

    def __init__(self, spec: str, preconditions: Mapping[str, Sequence[str]],
                 decided: Mapping[str, Mapping[str, str]] | None = None, *, name: str = "inline rules",
                 fail_closed: bool = True, warnings: Mapping[str, str] | None = None) -> None:
        try:
            tools, self.writes = converter_spec(spec)
        except ValueError as exc:
            raise NotEmbeddable([f"spec: {exc}"]) from None
        self.tools: dict[str, Tool] = {t.name: t for t in tools}
        self._name = name
        self.fail_closed = fail_closed
        self.decided = {action: dict(labels) for action, labels in (decided or {}).items()}
        self.warnings = dict(warnings or {})
        """The set's word on each action whose rule is empty or not backed by its demonstrations (a tool without
        rules is allowed every call, as the service allows it)."""
        self.rules, problems = self._compile(preconditions)
        if problems:
            raise NotEmbeddable(problems)
        self._methods = {"USER.says", "AGENT.result", *(f"AGENT.{t}" for t in self.tools)}
        """The spec's methods (`Class.method`): the actions whose labels may name a violation."""

    @classmethod
    def from_set(cls, stored: PreconditionSet | Mapping[str, Any], *, fail_closed: bool = True) -> Guard:
        """From a stored set (`Client.get_set(reference)`), its spec, rules and how each rule was decided."""
        found = stored if isinstance(stored, PreconditionSet) else PreconditionSet.model_validate(stored)
        return cls(found.spec, found.preconditions, found.decided, name=found.reference, fail_closed=fail_closed,
                   warnings=found.warnings)

    @property
    def name(self) -> str:
        """The set's reference (`ps_...@n`), named in refusals."""
        return self._name

    def _compile(self, preconditions: Mapping[str, Sequence[str]]) -> tuple[dict[str, list[_Rule]], list[str]]:
        rules: dict[str, list[_Rule]] = {}
        problems: list[str] = []
        for action, texts in preconditions.items():
            cls, _, tool = action.partition(".")
            if cls != "AGENT" or tool not in self.tools:
                problems.append(f"{action}: not a tool of the spec (the guard judges tool calls)")
                continue
            scope = Scope(AGENT_SHAPE, self.tools[tool].params)
            compiled = rules.setdefault(tool, [])
            for text in texts:
                try:
                    compiled.append(_Rule(text, compile_rule(text, scope)))
                except OutsideGrammar as exc:
                    problems.append(f"{action}: rule {text!r}: {exc}")
        return rules, problems

    def check_actions(self, messages: Iterable[Mapping[str, Any]],
                      calls: Iterable[Mapping[str, Any]]) -> CheckResponse:
        """`/check-actions` in this process: each call (`{"name", "arguments"}`) judged after the whole history,
        and where the history itself broke a rule (`history_violation`)."""
        session = self.session(messages)
        return CheckResponse.model_construct(
            results=[session.check(c.get("name", ""), c.get("arguments", {})) for c in calls],
            history_violation=session.history_violation, judged_by="interpreter")

    def session(self, messages: Iterable[Mapping[str, Any]] = ()) -> Session:
        """A conversation's state, after `messages` (more with `add`)."""
        session = Session(self)
        for message in messages:
            session.add(message)
        return session

    def check(self, messages: Iterable[Mapping[str, Any]], name: str,
              arguments: str | Mapping[str, Any]) -> CallVerdict:
        """One call after a whole history (read from the start: an agent that keeps a `session()` does not)."""
        return self.session(messages).check(name, arguments)

    def judge(self, state: StateReader, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        tool = self.tools.get(name) if isinstance(name, str) else None
        if tool is None:
            return _verdict(str(name), False, error=f"{NO_SUCH_TOOL}: {str(name)[:100]!r} (the set's tools: "
                                                    f"{', '.join(sorted(self.tools)[:20])})")
        given = _parsed(arguments)
        try:
            call, _ = state.read_call({"name": name, "arguments": given}, "calls[0]")
        except PlaceError as exc:
            return self._unjudged(f"agent.{tool.name}(...)", str(exc))
        line = call_line(call, tool)
        status = self.status(tool.name)
        if len(line) > MAX_CALL_CHARS:
            return _verdict(line, False, error=TOO_LONG, status=status)
        problem = schema_problem(tool.name, tool.schema, given if given is not arguments else arguments or {})
        if problem is not None:  # refused before any rule is asked, as the service refuses it
            return _verdict(line, False, error=problem, status=status)
        frame = Frame(state.state, tuple(_tupled(call.arguments.get(p)) for p in tool.params))
        violations: list[str] = []
        errors: list[str] = []
        for rule in self.rules.get(tool.name, ()):
            try:
                if not rule.evaluate(frame):
                    violations.append(rule.text)
            except Exception as exc:  # a rule that raises is a broken rule, never a plain "not allowed"
                errors.append(f"precondition {clean(rule.text, RULE_CHARS)!r} of AGENT.{tool.name} raised "
                              f"{clean(type(exc).__name__, 100)}: {clean(str(exc))}")
        if not violations and not errors:
            return _verdict(line, True, status=status)
        return _verdict(line, False, [clean(v, VIOLATION_CHARS) for v in violations],
                        self._labels(line, violations), clean("; ".join(errors)) if errors else None, status)

    def broken(self, state: StateReader, call: Call) -> str | None:
        """Where a history's call broke its tool's rules, in the service's words (`engine.broken_text`): the
        program line the service renders it on, the call, the action and every rule that did not hold (one that
        raises does not hold). The history is what happened: its later calls are still read."""
        tool = self.tools[call.tool]
        frame = Frame(state.state, tuple(_tupled(call.arguments.get(p)) for p in tool.params))
        failed = [rule.text for rule in self.rules.get(tool.name, ()) if not _holds(rule, frame)]
        if not failed:
            return None
        rules = ", ".join(f"`{rule}`" for rule in failed)
        return (f"history, line {call.line + 1}: {call_line(call, tool)}: AGENT.{tool.name}'s "
                f"rule{'s' if len(failed) > 1 else ''} {rules} did not hold")

    def status(self, tool: str) -> tuple[str, RuleStatus]:
        """The action of a tool and what its rule rests on, read from the set's `decided` as the service reads it:
        a tool without rules is 'missing' (every call allowed because nothing is known)."""
        action = f"AGENT.{tool}"
        return action, rule_status([r.text for r in self.rules.get(tool, ())], self.decided.get(action, {}))

    def _labels(self, line: str, violations: list[str]) -> dict[str, str]:
        """How each violated rule was decided, read as the service reads it (`engine._labelled`): the labels of
        every action whose method the call's text names."""
        if not violations or not self.decided:
            return {}
        labels = {rule: label for action, found in self.decided.items()
                  if action in self._methods and f".{action.partition('.')[2]}(" in line
                  for rule, label in found.items()}
        return {v: labels[v] for v in violations if v in labels}

    def _unjudged(self, call: str, reason: str) -> CallVerdict:
        return _verdict(call, not self.fail_closed, error=f"not judged: {reason}")


def _parsed(arguments: str | Mapping[str, Any]) -> Any:
    """A call's arguments given as JSON text, parsed once for both the reader and the schema; anything else (and
    text that does not parse, which the reader then refuses in its own words) as given."""
    if isinstance(arguments, str) and arguments.strip():
        try:
            return parse_json(arguments)
        except (ValueError, RecursionError):
            return arguments
    return arguments


def _holds(rule: _Rule, frame: Frame) -> bool:
    try:
        return bool(rule.evaluate(frame))
    except Exception:  # as the sandbox judges a history: a rule that raises does not hold
        return False


class _HistoryReader(StateReader):
    """The state, and the first of the history's own calls whose rules did not hold before it."""

    def __init__(self, guard: Guard) -> None:
        super().__init__(guard.tools, guard.writes, "history")
        self.guard = guard
        self.violation: str | None = None

    def called(self, call: Call) -> None:
        if self.violation is None:
            self.violation = self.guard.broken(self, call)


class Session:
    """A conversation for the embedded guard: the state after its messages, updated one message at a time."""

    def __init__(self, guard: Guard) -> None:
        self.guard = guard
        self.reader = _HistoryReader(guard)
        self.messages = 0
        self.broken: InvalidInput | None = None
        """Why the history could not be read: every later call is judged unreadable."""

    def add(self, message: Mapping[str, Any]) -> None:
        """The next message (OpenAI chat format); `InvalidInput` with the service's 422 text and field for one
        the service would refuse, after which the session judges no call."""
        if self.broken is not None:
            raise self.broken
        try:
            plain = dict(message) if isinstance(message, Mapping) and not isinstance(message, dict) else message
            self.reader.message(self.messages, plain)
        except PlaceError as exc:
            self.broken = InvalidInput(str(exc), status=422, type="invalid_input", field=exc.where)
            raise self.broken from None
        finally:
            self.messages += 1

    def extend(self, messages: Iterable[Mapping[str, Any]]) -> None:
        for message in messages:
            self.add(message)

    @property
    def history_violation(self) -> str | None:
        """Where the messages so far first broke a rule (`/check-actions`' `history_violation`); None if never."""
        return self.reader.violation

    def check(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        """The verdict on calling `name(**arguments)` now."""
        if self.broken is not None:
            return self.guard._unjudged(str(name), f"the history could not be read: {self.broken.message}")
        return self.guard.judge(self.reader, name, arguments)

    async def acheck(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        return self.check(name, arguments)


class ServiceGuard:
    """The service judges (`/check-actions` with a stored set) with the whole history each time: for a set the
    embedded guard cannot take, or a deployment that wants the service's record of every check. Give a `Client`
    for `check`, an `AsyncClient` for `acheck` (a `Client` there runs in a thread)."""

    def __init__(self, client: Any, precondition_set: str, *, fail_closed: bool = True) -> None:
        self.client = client
        self.reference = precondition_set
        self.fail_closed = fail_closed

    @property
    def name(self) -> str:
        return self.reference

    def session(self, messages: Iterable[Mapping[str, Any]] = ()) -> ServiceSession:
        session = ServiceSession(self)
        for message in messages:
            session.add(message)
        return session


class ServiceSession:
    def __init__(self, guard: ServiceGuard) -> None:
        self.guard = guard
        self.messages: list[dict[str, Any]] = []
        self.history_violation: str | None = None
        """The service's word, at the last check, on where the history broke a rule (`Session`'s alike)."""

    def add(self, message: Mapping[str, Any]) -> None:
        self.messages.append(dict(message))

    def _call(self, name: str, arguments: str | Mapping[str, Any]) -> dict[str, Any]:
        return {"name": name, "arguments": arguments if isinstance(arguments, str) else dict(arguments)}

    def _refused(self, name: str, exc: PrecondError) -> CallVerdict:
        return _verdict(str(name), not self.guard.fail_closed, error=f"not judged: {exc.message}")

    def check(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        try:
            answer = self.guard.client.check_with_set(self.guard.reference, self.messages,
                                                      [self._call(name, arguments)])
        except PrecondError as exc:
            return self._refused(name, exc)
        self.history_violation = answer.history_violation
        return answer.results[0]  # type: ignore[no-any-return]

    async def acheck(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        if not asyncio.iscoroutinefunction(self.guard.client.check_with_set):
            return await asyncio.to_thread(self.check, name, arguments)
        try:
            answer = await self.guard.client.check_with_set(self.guard.reference, self.messages,
                                                            [self._call(name, arguments)])
        except PrecondError as exc:
            return self._refused(name, exc)
        self.history_violation = answer.history_violation
        return answer.results[0]  # type: ignore[no-any-return]


READ_FIRST = re.compile(r"(\w+) in self\.results\[['\"](\w+)['\"]\]")
"""A rule that a read makes hold: the call's argument among that read tool's results."""


def refusal(verdict: CallVerdict, guard: str) -> str:
    """What the model reads in place of the tool's result: why the call was refused, so that it can recover.
    It starts with "Error" so that the history read later records a failed call (`openai_log.outcome`)."""
    reasons = [f"the rule `{rule}` does not hold" + (f" (decided: {verdict.decided[rule]})"
                                                        if rule in verdict.decided else "")
               for rule in verdict.violations]
    if verdict.error:
        reasons.append(verdict.error)
    return (f"Error: the precondition guard ({guard}) refused {verdict.call}: {'; '.join(reasons) or 'refused'}. "
            f"The tool did not run. {_way_out(verdict)}")


def _way_out(verdict: CallVerdict) -> str:
    """What the model can do about a refusal, naming only what a call of its own can change: a read the rule
    waits for (a rule that is only `x in self.results['read_tool']`), or the arguments that break the tool's
    schema. What a rule asks of what the records say (a delivered order's status) no call changes."""
    if verdict.error is not None and verdict.error.startswith(SCHEMA_BROKEN):
        return "Call it again with arguments that keep the tool's schema."
    reads = [m for m in (READ_FIRST.fullmatch(rule.strip()) for rule in verdict.violations) if m]
    if reads:  # the other rules may ask what the read returns: said by the next refusal, if any
        named = ", ".join(dict.fromkeys(f"{m.group(2)} for {m.group(1)}" for m in reads))
        return f"Call {named} first, then this call again."
    return "No call of yours can change what its rule asks: tell the user why this cannot be done."
