"""Isolated execution of untrusted programs and assertions for precondition reasoning.

The worker never executes untrusted code itself: everything goes through `Sandbox`, which runs it in
forked children of warm, stdlib-only fork servers under OS limits.
"""

from sandbox.api import Sandbox
from sandbox.limits import DEFAULT_ALLOWED_IMPORTS
from sandbox.types import (
    ActionInfo,
    CallVerdict,
    CandidateResult,
    EvaluateResult,
    LimitExceeded,
    Limits,
    Point,
    Position,
    ProgramError,
    SandboxCrashed,
    SandboxError,
    TraceResult,
)

__all__ = [
    "DEFAULT_ALLOWED_IMPORTS",
    "ActionInfo",
    "CallVerdict",
    "CandidateResult",
    "EvaluateResult",
    "LimitExceeded",
    "Limits",
    "Point",
    "Position",
    "ProgramError",
    "Sandbox",
    "SandboxCrashed",
    "SandboxError",
    "TraceResult",
]
