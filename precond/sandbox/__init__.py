"""Isolated execution of untrusted programs and assertions for precondition reasoning.

The worker never executes untrusted code itself: everything goes through `Sandbox`, which runs it in
forked children of warm, stdlib-only fork servers, each child confined by a seccomp allowlist and OS
limits before any untrusted byte runs (docs/security.md says what holds at which level).
"""

from precond.sandbox.api import Sandbox
from precond.sandbox.limits import DEFAULT_ALLOWED_IMPORTS
from precond.sandbox.types import (
    ActionInfo,
    BrokenRule,
    CallVerdict,
    CandidateResult,
    EvaluateResult,
    Judged,
    LimitExceeded,
    Limits,
    Point,
    PointGrid,
    Position,
    ProgramError,
    SandboxCancelled,
    SandboxCrashed,
    SandboxError,
    SandboxUnavailable,
    TraceResult,
)

__all__ = [
    "DEFAULT_ALLOWED_IMPORTS",
    "ActionInfo",
    "BrokenRule",
    "CallVerdict",
    "CandidateResult",
    "EvaluateResult",
    "Judged",
    "LimitExceeded",
    "Limits",
    "Point",
    "PointGrid",
    "Position",
    "ProgramError",
    "Sandbox",
    "SandboxCancelled",
    "SandboxCrashed",
    "SandboxError",
    "SandboxUnavailable",
    "TraceResult",
]
