"""A conversation that an agent framework hands over whole at each step, kept in a guard session message by
message: what was seen is remembered, and only what follows it is added."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from precond_client.errors import PrecondError
from precond_client.guard import GuardSession, Judge
from precond_client.schemas import CallVerdict

ToMessages = Callable[[Sequence[Any]], list[dict[str, Any]]]
"""A framework's items → OpenAI chat messages."""


class Conversation:
    """The session after a framework's list of items. A list that extends the one seen before (its last item is
    where the old one ended) adds only the new items; any other list (trimmed, filtered, another conversation)
    starts a new session from the whole list. A message the guard cannot read leaves the session broken: its
    calls are judged unreadable (refused, unless the guard fails open)."""

    def __init__(self, judge: Judge, to_messages: ToMessages) -> None:
        self.judge = judge
        self.to_messages = to_messages
        self.session: GuardSession = judge.session()
        self.seen = 0
        self.last: Any = None
        self.lock = threading.Lock()

    def follow(self, items: Sequence[Any]) -> GuardSession:
        with self.lock:
            if self.seen and (len(items) < self.seen or (items[self.seen - 1] is not self.last
                                                          and items[self.seen - 1] != self.last)):
                self.session, self.seen = self.judge.session(), 0
            new = items[self.seen:]
            if new:
                try:
                    for message in self.to_messages(new):
                        self.session.add(message)
                except PrecondError:
                    pass  # the session keeps why; each of its calls is refused with it
                self.seen, self.last = len(items), items[-1]
            return self.session


def unjudged(judge: Judge, call: str, reason: str) -> CallVerdict:
    """A call the guard never saw the conversation of: refused (or, failing open, allowed) with the reason."""
    return CallVerdict.model_construct(call=call, allowed=not judge.fail_closed, violations=[], decided={},
                                       error=f"not judged: {reason}")
