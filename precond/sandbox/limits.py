"""Limits as they travel to the fork server, and how long the parent waits for it.

The fork server enforces every limit itself; the parent only adds a grace period on top of the wall clock
so that a wedged server (not a slow child) is what its own deadline catches.
"""

from __future__ import annotations

from dataclasses import asdict

from precond.sandbox.types import Limits

# Modules untrusted specs may import; all of them are pre-imported by the fork server, which also blocks
# any import of a module it has not loaded.
DEFAULT_ALLOWED_IMPORTS: frozenset[str] = frozenset({
    "collections", "dataclasses", "typing", "enum", "math", "itertools", "functools", "re", "string",
    "copy", "abc",
})

# Seconds the parent waits beyond `timeout_s`: the server must kill the child, remove its directory
# and send up to `result_bytes` back.
SERVER_GRACE_S = 10.0


def validate(limits: Limits) -> Limits:
    """Reject limits that would disable a protection (0 or negative) instead of silently running unbounded."""
    for name, value in asdict(limits).items():
        if value <= 0:
            raise ValueError(f"limit {name} must be positive, got {value!r}")
    return limits


def to_wire(limits: Limits) -> dict[str, float | int]:
    return asdict(limits)


def parent_deadline_s(limits: Limits, warm: bool = False) -> float:
    """`warm`: a warm child may answer first; a failure there is run again on a fresh child with a whole wall
    clock of its own (`sandbox.child.server`), so the server may take two."""
    return limits.timeout_s * (2 if warm else 1) + SERVER_GRACE_S
