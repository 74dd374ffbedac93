"""The Sandbox facade: validates and filters in the parent, runs everything else in a fork server."""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Mapping, Sequence
from types import TracebackType
from typing import Any, TypeVar

from sandbox import protocol
from sandbox.astfilter import ProposedCall, check_program, expression_problem, parse_call
from sandbox.limits import DEFAULT_ALLOWED_IMPORTS, parent_deadline_s, to_wire, validate
from sandbox.pool import ServerPool
from sandbox.types import (
    CallVerdict,
    CandidateResult,
    EvaluateResult,
    Limits,
    Point,
    ProgramError,
    TraceResult,
)

log = logging.getLogger(__name__)
T = TypeVar("T")


class Sandbox:
    """Runs untrusted specs, demonstrations and assertions in warm fork servers; thread-safe.

    Every call forks a fresh child of a warm server, so calls never see each other's state and a child
    that hit a limit is gone. `workers` servers let that many calls run at once.
    """

    def __init__(self, limits: Limits | None = None, workers: int = 2, *,
                 allowed_imports: Collection[str] = DEFAULT_ALLOWED_IMPORTS) -> None:
        self.limits = validate(limits or Limits())
        self._pool = ServerPool(workers, to_wire(self.limits), allowed_imports)

    def __enter__(self) -> Sandbox:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self._pool.close()

    def trace(self, spec: str, demonstrations: Sequence[str]) -> TraceResult:
        """Positions of every demonstration and, for every spec method, where it was called with what."""
        _check_programs(spec, demonstrations, "demonstration")
        payload = {"spec": spec, "demonstrations": list(demonstrations)}
        return self._run("trace", payload, protocol.trace_result)

    def evaluate(self, spec: str, demonstrations: Sequence[str], candidates: Mapping[str, Sequence[str]],
                 points: Mapping[str, Sequence[Point]] | None = None) -> EvaluateResult:
        """Judge assertion candidates against the demonstrations and compute where each one holds.

        `points` replaces the default domain (demonstration × position × seen argument tuple) for the
        actions it names.
        """
        _check_programs(spec, demonstrations, "demonstration")
        problems = {a: [expression_problem(e) for e in exprs] for a, exprs in candidates.items()}
        sent = {a: [e for e, p in zip(exprs, problems[a], strict=True) if p is None]
                for a, exprs in candidates.items()}
        payload = {"spec": spec, "demonstrations": list(demonstrations), "candidates": sent,
                   "points": protocol.wire_points(points or {})}

        def build(result: dict[str, Any]) -> EvaluateResult:
            return _evaluate_result(result, candidates, problems, points or {})

        return self._run("evaluate", payload, build)

    def check(self, spec: str, preconditions: Mapping[str, Sequence[str]], history: str,
              calls: Sequence[str]) -> tuple[CallVerdict, ...]:
        """Run the history under the preconditions, then judge each proposed call on its own copy."""
        check_program(spec, "spec")
        check_program(history, "history")
        for action, expressions in preconditions.items():
            for expression in expressions:
                problem = expression_problem(expression)
                if problem is not None:
                    raise ProgramError("preconditions", None, None, "SyntaxError", f"{action}: {problem}")
        parsed = [parse_call(c) for c in calls]
        accepted = [p for p in parsed if isinstance(p, ProposedCall)]
        payload = {"spec": spec, "history": history,
                   "preconditions": {a: list(e) for a, e in preconditions.items()},
                   "calls": [protocol.wire_call(p) for p in accepted]}

        def build(result: dict[str, Any]) -> tuple[CallVerdict, ...]:
            verdicts = iter(result["verdicts"])
            return tuple(
                protocol.verdict(call, next(verdicts)) if isinstance(p, ProposedCall)
                else CallVerdict(call=call, allowed=False, error=f"rejected: {p}")
                for call, p in zip(calls, parsed, strict=True)
            )

        if not accepted:
            return build({"verdicts": []})
        return self._run("check", payload, build)

    def _run(self, op: str, payload: dict[str, Any], build: Callable[[dict[str, Any]], T]) -> T:
        message = {"op": op, "payload": payload}
        header, raw = self._pool.call(message, parent_deadline_s(self.limits))
        protocol.raise_for_header(header)
        return protocol.decode(raw, build)


def _check_programs(spec: str, programs: Sequence[str], where: str) -> None:
    check_program(spec, "spec")
    for index, source in enumerate(programs):
        check_program(source, where, index)


def _evaluate_result(result: dict[str, Any], candidates: Mapping[str, Sequence[str]],
                     problems: Mapping[str, list[str | None]],
                     custom: Mapping[str, Sequence[Point]]) -> EvaluateResult:
    points: dict[str, tuple[Point, ...]] = {}
    results: dict[str, tuple[CandidateResult, ...]] = {}
    for action, expressions in candidates.items():
        if action in custom:
            points[action] = tuple(custom[action])
        else:
            info = result["points"].get(action)
            points[action] = protocol.default_points(info) if info is not None else ()
        judged = iter(result["results"].get(action, []))
        results[action] = tuple(
            CandidateResult(e, "rejected", reason=problem) if problem is not None
            else protocol.candidate_result(e, next(judged))
            for e, problem in zip(expressions, problems[action], strict=True)
        )
    return EvaluateResult(points=points, results=results)
