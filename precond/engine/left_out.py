"""Demonstrations that cannot be judged within the sandbox's limits are left out, not the whole inference.

One oversized log (a tool result of megabytes) makes the trace of every demonstration run out of time or
memory together. The others still teach: the demonstrations are traced again one by one, each one that hits a
limit on its own is replaced by an empty program (the indices of the rest, which evidence and labels cite, stay
as they are) and named in the answer's warnings with the limit and the setting that would let it in. Only when
every demonstration hits a limit alone, or none does (together they are too much: the request's failure), does
the inference fail as before.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from precond.sandbox.types import LimitExceeded, Limits, TraceResult

if TYPE_CHECKING:
    from precond.sandbox import Sandbox

SETTINGS = {"timeout": ("SANDBOX_TIMEOUT_S", "timeout_s", "s"), "cpu": ("SANDBOX_CPU_S", "cpu_s", "s"),
            "memory": ("SANDBOX_MEMORY_MB", "memory_mb", "MB"),
            "output": ("SANDBOX_OUTPUT_BYTES", "output_bytes", "bytes"),
            "result": ("SANDBOX_RESULT_BYTES", "result_bytes", "bytes")}
"""The limits one demonstration can hit by its size alone, and the setting (and `Limits` field) that raises each.
Any other limit (`work`: the points of all demonstrations together) stays the request's failure."""
EMPTY = ""
"""What a left-out demonstration becomes: a program with no step, so it teaches nothing and runs at once."""


@dataclass(frozen=True)
class Traced:
    """The trace of the demonstrations that are judged, those demonstrations (a left-out one empty, at its index),
    and why each left-out one is (by index)."""

    trace: TraceResult
    demonstrations: list[str]
    left_out: dict[int, str] = field(default_factory=dict)


def trace_judgeable(sandbox: Sandbox, spec: str, demonstrations: Sequence[str], scope: str) -> Traced:
    """The demonstrations' trace; when it hits a per-call limit, the one(s) that hit it alone are left out."""
    demos = list(demonstrations)
    try:
        return Traced(sandbox.trace(spec, demos, scope=scope), demos)
    except LimitExceeded as exc:
        if exc.limit not in SETTINGS or len(demos) < 2:
            raise
        together = exc
    left_out = {}
    for index, demo in enumerate(demos):
        try:
            sandbox.trace(spec, [demo], scope=scope)
        except LimitExceeded as exc:
            if exc.limit not in SETTINGS:
                raise
            left_out[index] = exc.limit
    if not left_out or len(left_out) == len(demos):
        raise together
    kept = [EMPTY if i in left_out else d for i, d in enumerate(demos)]
    reasons = {i: why(limit, sandbox.limits, len(demos) - len(left_out), len(demos[i]))
               for i, limit in left_out.items()}
    return Traced(sandbox.trace(spec, kept, scope=scope), kept, reasons)


def why(limit: str, limits: Limits, others: int, chars: int) -> str:
    """The warning for one left-out demonstration: what it hit, the setting that would let it in, what teaches."""
    setting, name, unit = SETTINGS[limit]
    return (f"left out: it hits the sandbox's {limit} limit even when run alone ({setting}={getattr(limits, name)} "
            f"{unit}; the program is {chars:,} characters): raise {setting} to learn from it, or shorten its "
            f"largest tool results; the rules are learned from the other {others} demonstration(s)")
