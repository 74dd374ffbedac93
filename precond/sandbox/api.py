"""The Sandbox facade: validates and filters in the parent, runs everything else in a fork server."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
from functools import lru_cache
from types import TracebackType
from typing import Any, TypeVar

from precond.programs.checks import ProgramProblem, remembered_spec_methods
from precond.sandbox import protocol
from precond.sandbox.astfilter import ProposedCall, check_program, expression_problem, parse_call
from precond.sandbox.limits import DEFAULT_ALLOWED_IMPORTS, parent_deadline_s, to_wire, validate
from precond.sandbox.plain import SpecVocabulary, is_plain, vocabulary
from precond.sandbox.policy import PolicyUnavailable, build_filter
from precond.sandbox.pool import ServerPool
from precond.sandbox.types import (
    TIMED_OUT,
    BrokenRule,
    CallVerdict,
    CandidateResult,
    EvaluateResult,
    Judged,
    LimitExceeded,
    Limits,
    Point,
    ProgramError,
    SandboxCancelled,
    SandboxUnavailable,
    TraceResult,
)

log = logging.getLogger(__name__)
T = TypeVar("T")
MAX_ISOLATED = 8
MAX_TIMED_OUT = 4
"""Candidates a call may lose to its time limit (each retried alone) before the call itself has failed."""
TOO_MANY_ISOLATED = (f"not a plain assertion, and more than {MAX_ISOLATED} such assertions in one request: "
                     "each is judged in a process of its own")


class Sandbox:
    """Runs untrusted specs, demonstrations and assertions in warm fork servers; thread-safe.

    Every call forks a fresh, kernel-confined child of a warm server, so calls never see each other's
    state and a child that hit a limit is gone. `workers` servers let that many calls run at once.
    Without the kernel policy (no libseccomp, a kernel that refuses the filter) the constructor raises
    SandboxUnavailable, unless `allow_unconfined` (a development setting) is given.
    """

    def __init__(self, limits: Limits | None = None, workers: int = 2, *,
                 allowed_imports: Collection[str] = DEFAULT_ALLOWED_IMPORTS, allow_unconfined: bool = False) -> None:
        self.limits = validate(limits or Limits())
        self.unconfined_reason: str | None = None
        try:
            seccomp: bytes | None = build_filter()
        except PolicyUnavailable as exc:
            if not allow_unconfined:
                raise SandboxUnavailable(str(exc)) from exc
            seccomp = None
        self._local = threading.local()
        self._pool = ServerPool(workers, to_wire(self.limits), allowed_imports, seccomp, allow_unconfined)
        if not self._pool.hello.get("confined"):
            self.unconfined_reason = str(self._pool.hello.get("reason"))

    @property
    def boundary(self) -> dict[str, object]:
        """What the fork servers' probe found: `confined` (and why not), and whether the extra empty network
        namespace could be made (`network_namespace`, `detail`)."""
        hello = self._pool.hello
        return {key: hello.get(key) for key in ("confined", "reason", "network_namespace", "detail")}

    def __enter__(self) -> Sandbox:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self._pool.close()

    @contextmanager
    def cancel_when(self, cancelled: Callable[[], bool]) -> Iterator[None]:
        """Within the block, calls of this thread stop within ~0.1 s once `cancelled()` is true: the running
        child is killed with its server (which is replaced) and the call raises SandboxCancelled."""
        previous = getattr(self._local, "cancelled", None)
        self._local.cancelled = cancelled
        try:
            yield
        finally:
            self._local.cancelled = previous

    def trace(self, spec: str, demonstrations: Sequence[str], scope: str | None = None) -> TraceResult:
        """Positions of every demonstration and, for every spec method, where it was called with what. `scope`:
        whose request (the tenant), under which what is read from its text is remembered."""
        _check_programs(spec, demonstrations, "demonstration", scope or "")
        payload = {"spec": spec, "demonstrations": list(demonstrations)}
        return self._run("trace", payload, lambda result, _units: protocol.trace_result(result))

    def evaluate(self, spec: str, demonstrations: Sequence[str], candidates: Mapping[str, Sequence[str]],
                 points: Mapping[str, Sequence[Point]] | None = None, scope: str | None = None) -> EvaluateResult:
        """Judge assertion candidates against the demonstrations and compute where each one holds.

        `points` replaces the default domain (demonstration × position × seen argument tuple) for the
        actions it names. Plain candidates share one child; every other candidate is judged in a child of
        its own (at most `MAX_ISOLATED` a call), so that none can change another's verdict. `scope`: as `trace`.
        """
        key = scope or ""
        _check_programs(spec, demonstrations, "demonstration", key)
        problems = {a: [expression_problem(e, key) for e in exprs] for a, exprs in candidates.items()}
        plain, isolated = _partition(spec, {a: [e for e, p in zip(exprs, problems[a], strict=True) if p is None]
                                            for a, exprs in candidates.items()}, key)
        base = {"spec": spec, "demonstrations": list(demonstrations), "max_points": self.limits.max_points,
                "points": protocol.wire_points(points or {})}
        judged: dict[tuple[str, str], CandidateResult] = {}
        found: dict[str, Sequence[Point]] = {}

        def collect(sent: Mapping[str, Sequence[str]]) -> Callable[[dict[str, Any], Mapping[int, Any]], None]:
            def build(result: dict[str, Any], units: Mapping[int, Any]) -> None:
                for action, info in result["points"].items():
                    found.setdefault(str(action), protocol.default_points(info))
                flat = [(a, e) for a, exprs in sent.items() for e in exprs]
                for k, (action, expression) in enumerate(flat):
                    judged[(action, expression)] = protocol.candidate_result(expression, units[k])
            return build

        alone = self._run_plain(base, plain, collect)
        for number, (action, expression) in enumerate([*alone, *isolated]):
            if number >= MAX_ISOLATED + len(alone):
                judged[(action, expression)] = CandidateResult(expression, "rejected", reason=TOO_MANY_ISOLATED)
                continue
            one = {action: [expression]}
            try:
                self._run("evaluate", dict(base, candidates=one), collect(one))
            except LimitExceeded as exc:
                if exc.limit != "timeout" or exc.unit is None:
                    raise  # the demonstrations themselves ran out of time: the request's failure
                retried = " (also when judged alone)" if (action, expression) in alone else ""
                judged[(action, expression)] = CandidateResult(expression, "rejected", reason=(
                    f"{TIMED_OUT}{retried}: {exc.message}"))
        return _evaluate_result(judged, found, candidates, problems, points or {})

    def _run_plain(self, base: dict[str, Any], plain: dict[str, list[str]],
                   collect: Callable[[Mapping[str, Sequence[str]]], Callable[[dict[str, Any], Mapping[int, Any]],
                                                                           None]]) -> list[tuple[str, str]]:
        """Judge the plain candidates in one child. One that is running when the call's time runs out is that
        candidate's failure, not the call's: it is returned to be retried once alone (a loaded machine may have
        slowed the whole call, not this candidate), and the others are judged again in two calls, each with
        the whole time: those done before it, and those not started."""
        alone: list[tuple[str, str]] = []
        groups = [[(a, e) for a, exprs in plain.items() for e in exprs]]
        while groups:
            flat = groups.pop()
            sent = {action: [e for a, e in flat if a == action] for action in plain}  # every action: its points
            try:
                self._run("evaluate", dict(base, candidates=sent), collect(sent))
            except LimitExceeded as exc:
                if exc.limit != "timeout" or exc.unit is None or not 0 <= exc.unit < len(flat) \
                        or len(alone) >= MAX_TIMED_OUT:
                    raise
                alone.append(flat[exc.unit])
                groups += [part for part in (flat[exc.unit + 1:], flat[:exc.unit]) if part]
        return alone

    def check(self, spec: str, preconditions: Mapping[str, Sequence[str]], history: str,
              calls: Sequence[str], scope: str | None = None, warm: bool = True) -> tuple[CallVerdict, ...]:
        """`judge`'s verdicts on the calls."""
        return self.judge(spec, preconditions, history, calls, scope, warm).verdicts

    def judge(self, spec: str, preconditions: Mapping[str, Sequence[str]], history: str,
              calls: Sequence[str], scope: str | None = None, warm: bool = True) -> Judged:
        """Run the history under the preconditions, then judge each proposed call on its own copy, and say
        where the history itself first broke a rule (it is what happened: that never refuses a call).

        Plain preconditions are judged together; any other precondition in a child of its own, and a call
        is allowed only when every child allows it. `scope` (the caller's tenant) lets a warm child that
        answered this scope before, and no other, answer again with what it compiled then; `warm=False` runs
        the call on a fresh child all the same, for an answer that must not depend on what the scope ran
        before (one that is shared with other tenants).
        """
        key = scope or ""
        check_program(spec, "spec", scope=key)
        check_program(history, "history", scope=key)
        for action, expressions in preconditions.items():
            for expression in expressions:
                problem = expression_problem(expression, key)
                if problem is not None:
                    raise ProgramError("preconditions", None, None, "SyntaxError", f"{action}: {problem}")
        parsed = [parse_call(c) for c in calls]
        accepted = [p for p in parsed if isinstance(p, ProposedCall)]
        if parsed and not accepted:  # no call to judge (none sent: the history alone is)
            return Judged(tuple(_rejected(c, p) for c, p in zip(calls, parsed, strict=True)), None)
        plain, isolated = _partition(spec, preconditions, key)
        groups = [plain] + [{action: [expression]} for action, expression in isolated[:MAX_ISOLATED]]
        if len(isolated) > MAX_ISOLATED:
            raise ProgramError("preconditions", None, None, "ValueError", TOO_MANY_ISOLATED)
        wire_calls = [protocol.wire_call(p) for p in accepted]

        def build(_result: dict[str, Any], units: Mapping[int, Any]) -> tuple[list[CallVerdict], BrokenRule | None]:
            return ([protocol.verdict(p.text, units[k]) for k, p in enumerate(accepted)],
                    protocol.broken_rule(units.get(len(accepted))))

        parts = [  # an isolated precondition gets a child of its own: a fresh one, never a warm one
            self._run("check", {"spec": spec, "history": history, "calls": wire_calls,
                                "preconditions": {a: list(e) for a, e in group.items()}}, build,
                      scope if number == 0 and warm else None)
            for number, group in enumerate(groups)
        ]
        combined = iter([protocol.combine(verdicts) for verdicts in zip(*(v for v, _ in parts), strict=True)])
        verdicts = tuple(next(combined) if isinstance(p, ProposedCall) else _rejected(c, p)
                         for c, p in zip(calls, parsed, strict=True))
        return Judged(verdicts, protocol.first_broken([broken for _, broken in parts]))

    def _run(self, op: str, payload: dict[str, Any], build: Callable[[dict[str, Any], Mapping[int, Any]], T],
             scope: str | None = None) -> T:
        message = {"op": op, "payload": payload}
        cancelled = getattr(self._local, "cancelled", None)
        if cancelled is not None and cancelled():
            raise SandboxCancelled("cancelled")
        header, raw = self._pool.call(message, parent_deadline_s(self.limits, warm=scope is not None), cancelled,
                                      scope)
        protocol.raise_for_header(header)
        return protocol.decode(raw, build)


def _rejected(call: str, problem: ProposedCall | str) -> CallVerdict:
    return CallVerdict(call=call, allowed=False, error=f"rejected: {problem}")


def _check_programs(spec: str, programs: Sequence[str], where: str, scope: str) -> None:
    check_program(spec, "spec", scope=scope)
    for index, source in enumerate(programs):
        check_program(source, where, index, scope)


def _partition(spec: str, expressions: Mapping[str, Sequence[str]], scope: str = ""
               ) -> tuple[dict[str, list[str]], list[tuple[str, str]]]:
    """Plain expressions by action (every action kept, so its points are computed), and the others. What is
    read from the spec and the rules is remembered per scope (a tenant's checks repeat both)."""
    words = vocabulary(spec, scope)
    params = _parameters(scope, spec)
    plain: dict[str, list[str]] = {}
    isolated: list[tuple[str, str]] = []
    for action, exprs in expressions.items():
        plain[action] = []
        for expression in exprs:
            if _is_plain(scope, expression, params.get(action, ()), words):
                plain[action].append(expression)
            else:
                isolated.append((action, expression))
    return plain, isolated


@lru_cache(maxsize=1024)
def _is_plain(_scope: str, expression: str, params: tuple[str, ...], words: SpecVocabulary) -> bool:
    return is_plain(expression, params, words)


def _parameters(scope: str, spec: str) -> dict[str, tuple[str, ...]]:
    try:
        _, methods = remembered_spec_methods(scope, spec)
    except ProgramProblem:
        return {}
    return {q: (*m.positional, *((m.vararg,) if m.vararg else ())) for q, m in methods.items()}


def _evaluate_result(judged: Mapping[tuple[str, str], CandidateResult], found: Mapping[str, Sequence[Point]],
                     candidates: Mapping[str, Sequence[str]], problems: Mapping[str, list[str | None]],
                     custom: Mapping[str, Sequence[Point]]) -> EvaluateResult:
    points = {action: custom[action] if action in custom else found.get(action, ()) for action in candidates}
    results = {
        action: tuple(judged[(action, e)] if problem is None else CandidateResult(e, "rejected", reason=problem)
                      for e, problem in zip(expressions, problems[action], strict=True))
        for action, expressions in candidates.items()
    }
    return EvaluateResult(points=points, results=results)
