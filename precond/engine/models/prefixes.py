"""Key/value caches of prompt prefixes, kept per scope (a tenant) so that one tenant's work never helps,
slows or reveals another's.

Keeping a prefix's cache is what makes the next call with the same spec and demonstrations cheap (a dialog's
next turn re-runs only what is new). Shared across tenants it would be a side channel: a request that
reuses another tenant's cached prefix answers measurably faster, which tells the caller that somebody sent
that text recently (the prompt-caching attack). So entries are looked up only within the scope that made
them, and one tenant's entries are evicted only by that tenant (or by time): tenants share the memory's bound,
never each other's entries.

The bound is counted in the bytes of the kept keys and values, not in tokens: what a token costs depends on the
dtype the model runs in (12,288 bytes for the embedded 0.5B model in bfloat16, twice that in float32, which
`MODEL_DTYPE=auto` picks on CPUs without bf16 dot products), and a worker is sized by memory.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
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


def tenant_of(scope: str) -> str:
    """A scope is a tenant, or a tenant and a trained policy's adapter (`tenant\0adapter`): both count against
    that tenant's bound."""
    return scope.split("\0", 1)[0]


class PrefixStore:
    """Kept prefixes within two bounds: `max_bytes` over all tenants (what a worker is sized for) and
    `tenant_bytes` for each tenant. A tenant's new entry evicts only that tenant's own entries; when the rest of
    the store leaves no room it is not kept, so no tenant's prompt ever evicts another's (which would slow the
    other down and tell the first that somebody else was active). An entry unused for `idle_s` goes, so memory a
    tenant stopped using comes back without anybody's request taking it. One entry larger than a bound is kept
    alone, in a store nobody else holds anything in: a single dialog's next turn still reuses a long prompt."""

    def __init__(self, max_bytes: int, tenant_bytes: int | None = None, idle_s: float = 600.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.max_bytes = max_bytes
        self.tenant_bytes = max_bytes if tenant_bytes is None else tenant_bytes
        self.idle_s = idle_s
        self._clock = clock
        self._entries: OrderedDict[tuple[str, tuple[int, ...]], Prefix] = OrderedDict()
        self._sizes: dict[tuple[str, tuple[int, ...]], int] = {}
        """Each entry's bytes, counted once when it is kept (a kept cache is only read, never grown)."""
        self._used: dict[tuple[str, tuple[int, ...]], float] = {}
        self.held_bytes = 0
        self._held_by: dict[str, int] = {}
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
            self._expire()
            exact = self._entries.get((scope, tokens))
            if exact is not None:
                self._touch((scope, tokens))
                return exact, len(tokens)
            for (owner, kept), entry in self._entries.items():
                if owner != scope:
                    continue
                shared = common_length(kept, tokens)
                if shared > length:
                    best, length = entry, shared
            if best is not None:
                self._touch((scope, best.tokens))
        return best, length

    def put(self, scope: str, entry: Prefix) -> None:
        """Keep `entry` if it fits: first this tenant's own least recently used entries go, down to its bound and
        to the store's; other tenants' entries never do.

        An entry of the scope that `entry` extends goes at once: every lookup it answered, `entry` answers at
        least as far (a dialog's next turn extends the last one's prompt, and kept both would hold the shared
        part twice), and a repeat of the shorter prompt recomputes at most its last partial chunk."""
        size, tenant = self.size(entry), tenant_of(scope)
        with self._lock:
            self._expire()
            for owner, kept in list(self._entries):
                if owner == scope and len(kept) < len(entry.tokens) and entry.tokens[: len(kept)] == kept:
                    self._drop((owner, kept))
            key = (scope, entry.tokens)
            if key in self._entries:
                self._drop(key)
            self._evict_own(tenant, lambda: self._held_by.get(tenant, 0) + size > self.tenant_bytes)
            self._evict_own(tenant, lambda: self.held_bytes + size > self.max_bytes)
            fits = size <= self.tenant_bytes and self.held_bytes + size <= self.max_bytes
            if fits or self.held_bytes == 0:
                self._entries[key] = entry
                self._sizes[key] = size
                self._held_by[tenant] = self._held_by.get(tenant, 0) + size
                self.held_bytes += size
                self._used[key] = self._clock()

    def _evict_own(self, tenant: str, over: Callable[[], bool]) -> None:
        """Drop `tenant`'s least recently used entries while `over()` holds and it has any left."""
        while over():
            own = next((key for key in self._entries if tenant_of(key[0]) == tenant), None)
            if own is None:
                return
            self._drop(own)

    def _touch(self, key: tuple[str, tuple[int, ...]]) -> None:
        self._entries.move_to_end(key)
        self._used[key] = self._clock()

    def _expire(self) -> None:
        """Entries unused for `idle_s` go (least recently used first, so the scan stops at the first fresh one)."""
        cutoff = self._clock() - self.idle_s
        while self._entries:
            oldest = next(iter(self._entries))
            if self._used[oldest] > cutoff:
                return
            self._drop(oldest)

    def _drop(self, key: tuple[str, tuple[int, ...]]) -> None:
        del self._entries[key]
        del self._used[key]
        size = self._sizes.pop(key)
        self.held_bytes -= size
        tenant = tenant_of(key[0])
        self._held_by[tenant] -= size
        if not self._held_by[tenant]:
            del self._held_by[tenant]

    def scopes(self) -> set[str]:
        with self._lock:
            return {owner for owner, _ in self._entries}
