"""Values that cross from untrusted code into results: errors, argument values and text, all bounded."""

from __future__ import annotations

MESSAGE_CHARS = 500


class Failure(Exception):
    """A structured error for the caller (bad program, limit), as opposed to a bug in the sandbox."""

    def __init__(self, info: dict[str, object]) -> None:
        super().__init__(info.get("message"))
        self.info = info


class OutputLimit(BaseException):
    """Untrusted output went over its budget; BaseException so that `except Exception` cannot swallow it."""


FATAL = (MemoryError, OutputLimit)


def clean(text: str, limit: int = MESSAGE_CHARS) -> str:
    """Make untrusted text safe for JSON/HTTP: no lone surrogates, bounded length."""
    safe = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return safe if len(safe) <= limit else safe[: limit - 3] + "..."


def describe(exc: BaseException) -> tuple[str, str]:
    """Type name and message of an untrusted exception; a `__str__` that raises gives no message."""
    name = clean(type(exc).__name__, 100)
    try:
        message = str(exc)
    except FATAL:
        raise
    except BaseException:
        message = ""
    if not isinstance(message, str):
        message = ""
    return name, clean(message)


MAX_DEPTH = 16
MAX_ITEMS = 10_000
"""Nesting, and items in all, of the lists and objects one argument value keeps; past either (a value that
contains itself, twice over) the rest travels as its repr, so that no demonstration can make the boundary
recurse without end or copy without bound."""


def jsonable(value: object, depth: int = 0, budget: list[int] | None = None) -> object:
    """Argument values as JSON values; anything else travels as its (clean) repr. A dict with string keys
    travels as an object: conditions read its fields (`x['payment_id']` of each payment method), which its
    repr would not let them."""
    if value is None or isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        return value
    left = [MAX_ITEMS] if budget is None else budget
    if isinstance(value, (list, tuple)) and _take(left, len(value), depth):
        return [jsonable(v, depth + 1, left) for v in value]
    if type(value) is dict and all(type(k) is str for k in value) and _take(left, len(value), depth):
        return {clean(k, 200): jsonable(v, depth + 1, left) for k, v in value.items()}
    try:
        return clean(repr(value), 200)
    except FATAL:
        raise
    except BaseException:
        return clean(type(value).__name__, 100)


def _take(left: list[int], items: int, depth: int) -> bool:
    """Whether a container of `items` at `depth` still fits the budget (and takes its share of it)."""
    if depth >= MAX_DEPTH or items > left[0]:
        return False
    left[0] -= items
    return True


def tupled(value: object) -> object:
    """JSON arrays back into tuples, the form argument values have at the caller."""
    if isinstance(value, list):
        return tuple(tupled(v) for v in value)
    return value

