"""A code model whose completions are remembered on disk, so configurations that ask the same question share it.

The unverified policy and Algorithm 1 both start every step with the greedy line of the same prompt; with the
answers remembered, the second configuration pays only for what differs (the resamples), and an interrupted
run does not pay twice. Completions are deterministic for a given prompt and seed, so a remembered answer is
the answer. Latency stays honest: a remembered completion adds the seconds it took when it was computed
(`replayed_s`), so a request's latency is what it would have cost without the memo (a little more, in fact:
the backend's prefix cache may have to catch up on the next computed call).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from precond.evaluation.cache import JsonCache

if TYPE_CHECKING:
    from precond.engine.models import CodeModel, StopRule


class MemoModel:
    def __init__(self, model: CodeModel, cache: JsonCache) -> None:
        self.model = model
        self.cache = cache
        self.info = model.info
        self.known_calls = model.known_calls
        self.replayed_s = 0.0

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: StopRule,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        adapter = [self.info.adapter] if self.info.adapter else []  # a fine-tuned policy answers differently
        key = hashlib.sha256(json.dumps([prefix, list(suffixes), n, repr(sampling), stop, *adapter]).encode()
                             ).hexdigest()
        stored = self.cache.get("completions", key[:2], key)
        if stored is not None:
            self.replayed_s += stored["seconds"]
            return [list(texts) for texts in stored["texts"]]
        start = time.perf_counter()
        texts = self.model.complete(prefix, suffixes, n, sampling, stop, should_stop)
        self.cache.put({"texts": texts, "seconds": time.perf_counter() - start}, "completions", key[:2], key)
        return texts

    def take_replayed(self) -> float:
        """Seconds of remembered completions since the last call; resets the count."""
        seconds, self.replayed_s = self.replayed_s, 0.0
        return seconds

    def score(self, prefix: str, continuations: Sequence[str],
              should_stop: Callable[[], bool] | None = None) -> list[float]:
        return self.model.score(prefix, continuations, should_stop)
