"""What crosses the sandbox boundary, as the worker sees it.

The sandbox knows nothing of HTTP, Redis or pydantic: plain frozen dataclasses keep it importable by any
caller and cheap to construct. Argument values are JSON values (str, int, float, bool, None, lists, objects
with string keys), because JSON is the only thing that crosses the process boundary.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, overload

JSONScalar = str | int | float | bool | None
Args = tuple[object, ...]


class Record(dict[str, object]):
    """An argument that is an object (`{'payment_id': 'certificate_1', 'amount': 50}`): a dict to the conditions
    judged on it, hashable here because a Point is a key. Its values are frozen too (lists as tuples)."""

    def __hash__(self) -> int:  # type: ignore[override]
        return hash(tuple(sorted(self.items())))


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
    unit_cpu_s: float = 2.0  # one candidate or one proposed call; over it, that part fails alone
    max_failed_units: int = 8  # parts that may fail on a limit before the whole call does
    max_points: int = 2_000_000  # points (positions × argument tuples) of one action, judged per candidate


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


class PointGrid(Sequence[Point]):
    """An action's default points, demonstration positions × argument tuples, without building the
    product: a request that names thousands of argument values costs the worker two short lists, and
    `index` answers in constant time."""

    def __init__(self, positions: Sequence[tuple[int, int]], values: Sequence[Args]) -> None:
        self._positions, self._values = tuple(positions), tuple(values)
        self._position_index = {p: i for i, p in enumerate(self._positions)}
        self._value_index = {v: i for i, v in enumerate(self._values)}

    def __len__(self) -> int:
        return len(self._positions) * len(self._values)

    @overload
    def __getitem__(self, k: int) -> Point: ...

    @overload
    def __getitem__(self, k: slice) -> Sequence[Point]: ...

    def __getitem__(self, k: int | slice) -> Point | Sequence[Point]:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        demo, position = self._positions[k // len(self._values)]
        return Point(demo, position, self._values[k % len(self._values)])

    def index(self, value: object, start: int = 0, stop: int | None = None) -> int:
        if isinstance(value, Point):
            p = self._position_index.get((value.demo, value.position))
            v = self._value_index.get(value.args)
            if p is not None and v is not None:
                k = p * len(self._values) + v
                if start <= k < (len(self) if stop is None else stop):
                    return k
        raise ValueError(f"{value!r} is not a point of this grid")

    def __contains__(self, value: object) -> bool:
        try:
            self.index(value)
        except ValueError:
            return False
        return True

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, Sequence) and len(self) == len(other)
                and all(a == b for a, b in zip(self, other, strict=True)))

    __hash__ = None  # type: ignore[assignment]


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


TIMED_OUT = "dropped: ran out of time"
"""How the reason of a candidate dropped for running out of time starts (the engine counts them)."""

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
    points: dict[str, Sequence[Point]]
    results: dict[str, tuple[CandidateResult, ...]]


@dataclass(frozen=True)
class CallVerdict:
    call: str
    allowed: bool
    violations: tuple[str, ...] = field(default_factory=tuple)
    error: str | None = None


@dataclass(frozen=True)
class BrokenRule:
    """Where a history first called an action whose rules did not hold: the line, the action, those rules."""

    line: int
    action: str
    rules: tuple[str, ...]


@dataclass(frozen=True)
class Judged:
    """Proposed calls judged after a history, and where the history itself first broke a rule (None: never)."""

    verdicts: tuple[CallVerdict, ...]
    history: BrokenRule | None


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
        # `demonstrations[2]`: the request's field, as every message names a demonstration
        place = self.where if self.index is None else f"{self.where}s[{self.index}]"
        at = "" if self.line is None else f", line {self.line}"
        return f"{place}{at}: {self.exc_type}: {self.message}"


@dataclass
class LimitExceeded(SandboxError):
    """Untrusted code hit a limit; the child that ran it is gone."""

    limit: str  # "timeout" | "cpu" | "memory" | "output" | "recursion" | "result" | "work"
    message: str
    unit: int | None = None
    """The part of the call (a candidate's index in the call) that was running when the limit hit, if one was."""

    def __str__(self) -> str:
        return f"{self.limit} limit exceeded: {self.message}"


class SandboxUnavailable(SandboxError):
    """The kernel policy could not be set up here, so no untrusted code is run (fail closed)."""


class SandboxCrashed(SandboxError):
    """The child died without an answer (killed, segfault); it has been replaced."""


class SandboxCancelled(SandboxError):
    """The caller's cancel predicate turned true during a call: its server was killed (child included) and
    replaced; the call has no result."""
