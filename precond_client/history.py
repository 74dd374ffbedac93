"""Structured histories without code strings: `event("user", "INFORM", "city")`, or a `History` built step by
step. What an end user typed goes in as an argument, a literal the service renders with `repr`; it can never
become code, whatever quotes or newlines it holds."""

from __future__ import annotations

from collections.abc import Iterator

from precond_client.schemas import MAX_EVENT_ARGS, HistoryEvent

Arg = str | int | float | bool | None
"""What an event argument may be: a scalar. Anything else is refused here, before it is sent."""


def event(actor: str, act: str, *args: Arg) -> HistoryEvent:
    """One step, `actor.act(*args)`: e.g. `event("user", "INFORM", "city")`, `event("system", "GOODBYE")`."""
    if len(args) > MAX_EVENT_ARGS:
        raise ValueError(f"{actor}.{act}: {len(args)} arguments, at most {MAX_EVENT_ARGS}")
    for index, arg in enumerate(args):
        if arg is not None and not isinstance(arg, str | int | float | bool):
            raise TypeError(f"{actor}.{act}: argument {index} is a {type(arg).__name__}; an event argument is a "
                            "str, int, float, bool or None")
    return HistoryEvent(actor=actor, act=act, args=list(args))


class History:
    """A dialog's history as events, appended turn by turn; pass `history.events` (or the object's list) as a
    request's `history`.

    >>> history = History().add("user", "INFORM_INTENT", "FindRestaurants").add("system", "REQUEST", "city")
    >>> history.user("INFORM", "city")         # shorthand for add("user", ...)
    """

    def __init__(self, events: list[HistoryEvent] | None = None) -> None:
        self.events: list[HistoryEvent] = list(events or [])

    def add(self, actor: str, act: str, *args: Arg) -> History:
        self.events.append(event(actor, act, *args))
        return self

    def user(self, act: str, *args: Arg) -> History:
        return self.add("user", act, *args)

    def system(self, act: str, *args: Arg) -> History:
        return self.add("system", act, *args)

    def copy(self) -> History:
        return History(self.events)

    def __iter__(self) -> Iterator[HistoryEvent]:
        return iter(self.events)

    def __len__(self) -> int:
        return len(self.events)
