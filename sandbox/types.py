"""What crosses the sandbox boundary, as the worker sees it.

The sandbox knows nothing of HTTP, Redis or pydantic: plain frozen dataclasses keep it importable by any
caller and cheap to construct. Argument values are JSON values (str, int, float, bool, None, lists), because
JSON is the only thing that crosses the process boundary.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

JSONScalar = str | int | float | bool | None
Args = tuple[object, ...]


@dataclass(frozen=True)
class Limits:
    """Per-call limits on untrusted code; each is configurable because deployments differ."""

    timeout_s: float = 10.0
    cpu_s: int = 10
    memory_mb: int = 1024
    open_files: int = 64
    output_bytes: int = 1_000_000
    result_bytes: int = 64_000_000
    recursion: int = 400


@dataclass(frozen=True)
class Position:
    """One executed statement of a demonstration's main body (the paper's time step j)."""

    line: int
    source: str


@dataclass(frozen=True)
class Point:
    """A place where an action's precondition can be asked: demonstration i, before position j, with args."""

    demo: int
    position: int
    args: Args


@dataclass(frozen=True)
class ActionInfo:
    """A method of a spec class. `stub` methods (body only pass/.../docstring) are the default actions."""

    name: str
    params: tuple[str, ...]
    stub: bool
    occurrences: tuple[Point, ...]
    arg_values: tuple[Args, ...]


@dataclass(frozen=True)
class TraceResult:
    actions: dict[str, ActionInfo]
    positions: tuple[tuple[Position, ...], ...]


CandidateStatus = Literal["rejected", "invalid", "valid"]


@dataclass(frozen=True)
class CandidateResult:
    """One assertion expression. `satisfied` is a bitset over the action's points (bit k = points[k])."""

    expression: str
    status: CandidateStatus
    reason: str | None = None
    satisfied: int = 0


@dataclass(frozen=True)
class EvaluateResult:
    points: dict[str, tuple[Point, ...]]
    results: dict[str, tuple[CandidateResult, ...]]


@dataclass(frozen=True)
class CallVerdict:
    call: str
    allowed: bool
    violations: tuple[str, ...] = field(default_factory=tuple)
    error: str | None = None


class SandboxError(Exception):
    """Base of everything the sandbox raises; the caller's process is never harmed by untrusted code."""


@dataclass
class ProgramError(SandboxError):
    """The spec, a demonstration or the history does not parse or raises; `where` names which."""

    where: str  # "spec" | "demonstration" | "history" | "preconditions"
    index: int | None
    line: int | None
    exc_type: str
    message: str

    def __str__(self) -> str:
        place = self.where if self.index is None else f"{self.where} {self.index}"
        at = "" if self.line is None else f", line {self.line}"
        return f"{place}{at}: {self.exc_type}: {self.message}"


@dataclass
class LimitExceeded(SandboxError):
    """Untrusted code hit a limit; the child that ran it is gone."""

    limit: str  # "timeout" | "cpu" | "memory" | "output" | "recursion" | "result"
    message: str

    def __str__(self) -> str:
        return f"{self.limit} limit exceeded: {self.message}"


class SandboxCrashed(SandboxError):
    """The child died without an answer (killed, segfault); it has been replaced."""
