"""How every operation of the engine calls the sandbox and reads a history: the sandbox's failures turned into the
API's errors, a history rendered as the program the sandbox runs, the words of a broken rule."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from precond.convert.openai import structured_history
from precond.engine import scope
from precond.engine.spec import (
    as_error,
    parse_source,
)
from precond.programs import checks
from precond.sandbox.types import (
    BrokenRule,
    LimitExceeded,
    ProgramError,
    SandboxCancelled,
    SandboxCrashed,
    SandboxUnavailable,
)
from precond_client.schemas import (
    CheckRequest,
    HistoryEvent,
    NextActionRequest,
)
from precond_client.schemas.errors import (
    Cancelled,
    InvalidInput,
    InvalidProgram,
    ResourceLimit,
    SandboxFailure,
)

if TYPE_CHECKING:
    pass



T = TypeVar("T")

SANDBOX_FIELDS = {"spec": "spec", "history": "history", "preconditions": "preconditions"}

def sandbox_call(fn: Callable[..., T], *args: object, **kwargs: object) -> T:
    """Turn the sandbox's errors about untrusted input into the API's user-facing errors."""
    try:
        return fn(*args, **kwargs)
    except ProgramError as exc:
        where = f"demonstrations[{exc.index}]" if exc.where == "demonstration" else SANDBOX_FIELDS.get(exc.where)
        raise InvalidProgram(str(exc), field=where) from exc
    except LimitExceeded as exc:
        field = "demonstrations" if exc.limit == "work" else None  # points grow with demonstrations × arguments
        raise ResourceLimit(f"untrusted code hit the sandbox's {exc.limit} limit: {exc.message}", field=field) from exc
    except SandboxCancelled as exc:
        raise Cancelled("job cancelled") from exc
    except (SandboxCrashed, SandboxUnavailable) as exc:
        raise SandboxFailure(f"the sandbox failed, not the request (try again): {exc}") from exc


def broken_text(history: str, broken: BrokenRule | None) -> str | None:
    """Where a history broke a rule, in words: the line, its call, the action and the rules that did not hold."""
    if broken is None:
        return None
    lines = history.splitlines()
    call = lines[broken.line - 1].strip() if 0 < broken.line <= len(lines) else "?"
    rules = ", ".join(f"`{rule}`" for rule in broken.rules)
    return (f"history, line {broken.line}: {call}: {broken.action}'s rule{'s' if len(broken.rules) > 1 else ''} "
            f"{rules} did not hold")


def history_program(spec: str, history: str | Sequence[HistoryEvent | dict[str, Any]]) -> str:
    """A history as the program the sandbox runs (`rendered_history`), which must parse (a 422 if not)."""
    program = rendered_history(spec, history)
    parse_source(program, "history")
    return program


def rendered_history(spec: str, history: str | Sequence[HistoryEvent | dict[str, Any]]) -> str:
    """A history as the program the sandbox runs: code as sent, or structured events (or an agent's OpenAI
    messages) rendered with literals."""
    if isinstance(history, str):
        return history
    try:
        return structured_history(spec, [e if isinstance(e, dict) else e.model_dump() for e in history],
                                  scope=scope.current())
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc


def spec_of(request: CheckRequest | NextActionRequest) -> str:
    if request.spec is None:
        raise InvalidInput("precondition_set is resolved by the service: send `spec` and `preconditions` here",
                           field="precondition_set")
    return request.spec

