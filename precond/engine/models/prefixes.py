"""Key/value caches of prompt prefixes, kept per scope (a tenant) so that one tenant's work never helps,
slows or reveals another's.

Keeping a prefix's cache is what makes the next call with the same spec and demonstrations cheap (a dialog's
next turn re-runs only what is new). Shared across tenants it would be a side channel: a request that
reuses another tenant's cached prefix answers measurably faster, which tells the caller that somebody sent
that text recently (the prompt-caching attack). So entries are looked up only within the scope that made
them; scopes share only the bound on memory, counted in tokens, least recently used first.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Prefix:
    """The cache of `tokens`, computed in fixed chunks from position 0 (so reuse is bit-identical)."""

    tokens: tuple[int, ...] = ()
    cache: Any = None


def common_length(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    n = min(len(a), len(b))
    for i in range(n):
        if a[i] != b[i]:
            return i
    return n


class PrefixStore:
    def __init__(self, max_tokens: int) -> None:
        self.max_tokens = max_tokens
        self._entries: OrderedDict[tuple[str, tuple[int, ...]], Prefix] = OrderedDict()
        self._lock = threading.Lock()
        """The base model and its adapted copies share a store, and may run in two job threads at once."""

    def closest(self, scope: str, tokens: tuple[int, ...]) -> tuple[Prefix | None, int]:
        """This scope's entry sharing the longest token prefix with `tokens`, and that length."""
        best, length = None, 0
        with self._lock:
            exact = self._entries.get((scope, tokens))
            if exact is not None:
                self._entries.move_to_end((scope, tokens))
                return exact, len(tokens)
            for (owner, kept), entry in self._entries.items():
                if owner != scope:
                    continue
                shared = common_length(kept, tokens)
                if shared > length:
                    best, length = entry, shared
            if best is not None:
                self._entries.move_to_end((scope, best.tokens))
        return best, length

    def put(self, scope: str, entry: Prefix) -> None:
        """Keep `entry`, evicting least recently used entries (of any scope) beyond the token bound.

        An entry of the scope that `entry` extends goes at once: every lookup it answered, `entry` answers at
        least as far (a dialog's next turn extends the last one's prompt, and kept both would hold the shared
        part twice), and a repeat of the shorter prompt recomputes at most its last partial chunk."""
        with self._lock:
            for owner, kept in list(self._entries):
                if owner == scope and len(kept) < len(entry.tokens) and entry.tokens[: len(kept)] == kept:
                    del self._entries[(owner, kept)]
            self._entries[(scope, entry.tokens)] = entry
            self._entries.move_to_end((scope, entry.tokens))
            while len(self._entries) > 1 and sum(len(t) for _, t in self._entries) > self.max_tokens:
                self._entries.popitem(last=False)

    def scopes(self) -> set[str]:
        with self._lock:
            return {owner for owner, _ in self._entries}
