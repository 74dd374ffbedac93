"""Turning child results (JSON) into the types of ``sandbox.types``.

The child runs untrusted code, so its output is treated as hostile: every field is type-checked and every
string cleaned; anything malformed becomes SandboxCrashed instead of a confusing error deeper down.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

from precond.sandbox.astfilter import ProposedCall
from precond.sandbox.child.values import clean
from precond.sandbox.types import (
    ActionInfo,
    Args,
    BrokenRule,
    CallVerdict,
    CandidateResult,
    LimitExceeded,
    Point,
    PointGrid,
    Position,
    ProgramError,
    Record,
    SandboxCrashed,
    SandboxError,
    SandboxUnavailable,
    TraceResult,
)

T = TypeVar("T")
LIMIT_NAMES = frozenset({"timeout", "cpu", "memory", "output", "recursion", "result", "work"})


def as_args(value: object) -> Args:
    """JSON arrays as tuples and objects as Records, recursively, so that Points are hashable."""
    if not isinstance(value, list):
        raise TypeError("arguments must be a list")
    return tuple(_tupled(v) for v in value)


def _tupled(value: object) -> object:
    if isinstance(value, list):
        return tuple(_tupled(v) for v in value)
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return Record({k: _tupled(v) for k, v in value.items()})
    if isinstance(value, str):
        return value
    if value is None or isinstance(value, (bool, int, float)):
        return value
    raise TypeError("argument values must be JSON values")


def wire_args(args: Sequence[object]) -> list[object]:
    return [wire_args(a) if isinstance(a, (list, tuple)) else a for a in args]


def wire_points(points: Mapping[str, Sequence[Point]]) -> dict[str, list[list[object]]]:
    return {action: [[p.demo, p.position, wire_args(p.args)] for p in pts]
            for action, pts in points.items()}


def wire_call(call: ProposedCall) -> dict[str, object]:
    return {"target": call.target, "method": call.method, "args": wire_args(call.args),
            "kwargs": {k: wire_args(v) if isinstance(v, (list, tuple)) else v
                       for k, v in call.kwargs.items()}}


def raise_for_header(header: Mapping[str, Any]) -> None:
    """Server-side outcomes (timeouts, kills) as exceptions."""
    status = header.get("status")
    message = clean(str(header.get("message", "")))
    if status == "limit":
        unit = header.get("unit")
        raise LimitExceeded(_limit_name(header.get("limit")), message,
                            unit if isinstance(unit, int) and not isinstance(unit, bool) else None)
    if status == "unconfined":
        raise SandboxUnavailable(message)
    if status != "ok":
        raise SandboxCrashed(message or f"unexpected status {clean(str(status), 40)}")


def decode(payload: bytes, build: Callable[[dict[str, Any], Mapping[int, Any]], T]) -> T:
    """Parse a server reply (the child's final result and its units by index); raise the structured
    error it carries, or SandboxCrashed when it is malformed."""
    try:
        reply = json.loads(payload)
        result, units = reply["result"], reply["units"]
        if not isinstance(result, dict) or not isinstance(units, dict):
            raise TypeError("result is not an object")
        if "error" in result:
            raise _error(result["error"])
        return build(result, {int(k): v for k, v in units.items()})
    except SandboxError:
        raise
    except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as exc:
        raise SandboxCrashed(f"malformed result from the sandbox: {clean(str(exc))}") from None


def _limit_name(value: object) -> str:
    name = str(value)
    return name if name in LIMIT_NAMES else "timeout"


def _error(info: Mapping[str, Any]) -> SandboxError:
    kind = info.get("kind")
    message = clean(str(info.get("message", "")))
    if kind == "program":
        index, line = info.get("index"), info.get("line")
        return ProgramError(
            where=clean(str(info.get("where")), 40),
            index=index if isinstance(index, int) else None,
            line=line if isinstance(line, int) else None,
            exc_type=clean(str(info.get("exc_type")), 100),
            message=message,
        )
    if kind == "limit":
        return LimitExceeded(_limit_name(info.get("limit")), message)
    if kind == "bad_request":
        return SandboxError(f"bad request: {message}")
    return SandboxCrashed(f"sandbox internal error: {message}")


def trace_result(result: dict[str, Any]) -> TraceResult:
    positions = tuple(
        tuple(Position(int(line), clean(str(source), 2000)) for line, source in demo)
        for demo in result["positions"]
    )
    actions = {
        clean(str(name), 200): ActionInfo(
            name=clean(str(name), 200),
            params=tuple(clean(str(p), 100) for p in info["params"]),
            stub=bool(info["stub"]),
            occurrences=tuple(Point(int(d), int(p), as_args(a)) for d, p, a in info["occurrences"]),
            arg_values=tuple(as_args(a) for a in info["arg_values"]),
        )
        for name, info in result["actions"].items()
    }
    return TraceResult(actions=actions, positions=positions)


def default_points(info: Mapping[str, Any]) -> PointGrid:
    """The child sends positions and argument values; the product stays implicit."""
    return PointGrid([(int(d), int(p)) for d, p in info["positions"]], [as_args(v) for v in info["arg_values"]])


def candidate_result(expression: str, info: Mapping[str, Any]) -> CandidateResult:
    if "failed" in info:
        return CandidateResult(expression, "rejected", reason=clean(str(info["failed"])))
    status = info["status"]
    if status not in ("rejected", "invalid", "valid"):
        raise ValueError(f"unknown status {clean(str(status), 40)}")
    reason = info.get("reason")
    satisfied = info.get("satisfied")
    return CandidateResult(
        expression=expression,
        status=status,
        reason=None if reason is None else clean(str(reason)),
        satisfied=int(satisfied, 16) if isinstance(satisfied, str) else 0,
    )


def verdict(call: str, info: Mapping[str, Any]) -> CallVerdict:
    if "failed" in info:
        return CallVerdict(call=call, allowed=False, error=clean(str(info["failed"])))
    error = info.get("error")
    violations = info.get("violations") or []
    if not isinstance(violations, list):
        raise TypeError("violations must be a list")
    return CallVerdict(
        call=call,
        allowed=bool(info["allowed"]) and error is None and not violations,
        violations=tuple(clean(str(v), 4000) for v in violations),
        error=None if error is None else clean(str(error)),
    )


def broken_rule(info: Any) -> BrokenRule | None:
    """The history's own part of a check (`{"line", "action", "rules"}`); None when it broke no rule, or when that
    part failed (a runaway rule: the calls' verdicts name it)."""
    if not isinstance(info, Mapping) or "failed" in info or not isinstance(info.get("line"), int):
        return None
    rules = info.get("rules") or []
    if not isinstance(rules, list) or not rules:
        return None
    return BrokenRule(int(info["line"]), clean(str(info.get("action")), 200), tuple(clean(str(r), 4000) for r in rules))


def first_broken(parts: Sequence[BrokenRule | None]) -> BrokenRule | None:
    """The children's findings (plain rules, each other rule alone) as one: the first line, with every rule of
    that line's action that broke."""
    found = [p for p in parts if p is not None]
    if not found:
        return None
    line = min(p.line for p in found)
    at = [p for p in found if p.line == line]
    return BrokenRule(line, at[0].action, tuple(dict.fromkeys(r for p in at for r in p.rules)))


def combine(parts: Sequence[CallVerdict]) -> CallVerdict:
    """One call judged by several children (plain and isolated preconditions): allowed only if all allow."""
    errors = [p.error for p in parts if p.error]
    return CallVerdict(call=parts[0].call, allowed=all(p.allowed for p in parts),
                       violations=tuple(v for p in parts for v in p.violations),
                       error="; ".join(dict.fromkeys(errors)) or None)
