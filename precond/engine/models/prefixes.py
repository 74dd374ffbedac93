"""Key/value caches of prompt prefixes, kept per scope (a tenant) so that one tenant's work never helps,
slows or reveals another's.

Keeping a prefix's cache is what makes the next call with the same spec and demonstrations cheap (a dialog's
next turn re-runs only what is new). Shared across tenants it would be a side channel: a request that
reuses another tenant's cached prefix answers measurably faster, which tells the caller that somebody sent
that text recently (the prompt-caching attack). So entries are looked up only within the scope that made
them; scopes share only the bound on memory, least recently used first.

The bound is counted in the bytes of the kept keys and values, not in tokens: what a token costs depends on the
dtype the model runs in (12,288 bytes for the embedded 0.5B model in bfloat16, twice that in float32, which
`MODEL_DTYPE=auto` picks on CPUs without bf16 dot products), and a worker is sized by memory.
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
    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[tuple[str, tuple[int, ...]], Prefix] = OrderedDict()
        self._sizes: dict[tuple[str, tuple[int, ...]], int] = {}
        """Each entry's bytes, counted once when it is kept (a kept cache is only read, never grown)."""
        self.held_bytes = 0
        self._lock = threading.Lock()
        """The base model and its adapted copies share a store, and may run in two job threads at once."""

    @staticmethod
    def size(entry: Prefix) -> int:
        """The bytes of `entry`'s keys and values over all its layers, in whatever dtype they are held."""
        if entry.cache is None:
            return 0
        return sum(int(layer.keys.nbytes) + int(layer.values.nbytes) for layer in entry.cache.layers
                   if layer.keys is not None and layer.values is not None)

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
        """Keep `entry`, evicting least recently used entries (of any scope) beyond the byte bound. An entry
        larger than the whole bound is kept alone: its dialog's next turn still reuses it, so the store exceeds
        the bound by one prompt at most.

        An entry of the scope that `entry` extends goes at once: every lookup it answered, `entry` answers at
        least as far (a dialog's next turn extends the last one's prompt, and kept both would hold the shared
        part twice), and a repeat of the shorter prompt recomputes at most its last partial chunk."""
        size = self.size(entry)
        with self._lock:
            for owner, kept in list(self._entries):
                if owner == scope and len(kept) < len(entry.tokens) and entry.tokens[: len(kept)] == kept:
                    self._drop((owner, kept))
            key = (scope, entry.tokens)
            if key in self._entries:
                self._drop(key)
            self._entries[key] = entry
            self._sizes[key] = size
            self.held_bytes += size
            while len(self._entries) > 1 and self.held_bytes > self.max_bytes:
                self._drop(next(iter(self._entries)))

    def _drop(self, key: tuple[str, tuple[int, ...]]) -> None:
        del self._entries[key]
        self.held_bytes -= self._sizes.pop(key)

    def scopes(self) -> set[str]:
        with self._lock:
            return {owner for owner, _ in self._entries}
