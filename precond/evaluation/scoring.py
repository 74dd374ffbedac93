"""C_a on the test trajectories, computed by the sandbox, for predicted and ground-truth preconditions alike.

Predicted preconditions are model output, so they are only ever executed in the sandbox; ground truth goes
through the very same path, which makes the GT row (P = R = F1 = 1) a check of the whole pipeline rather
than of a second, trusted implementation.

An action's preconditions are scored as one expression, their conjunction (`True` when there are none):
the test trajectories are passed as the sandbox's "demonstrations", each action gets that single candidate
and the domain's explicit points, and the candidate's `satisfied` bitset is C_a. Whether the candidate is
"valid" on the test data (holds at every test occurrence) does not matter here; only where it holds does.

Satisfaction sets depend only on (domain, action, expression), so they are cached per expression: every
configuration that predicts the same assertions reuses them, and re-scoring is free.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Protocol

from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import ActionScore, score_action
from precond.sandbox.types import EvaluateResult, Point

CHUNK_TRAJECTORIES = 25
Progress = Callable[[int], None]


class Evaluator(Protocol):
    """The part of `sandbox.Sandbox` scoring needs (a protocol, so tests can count calls)."""

    def evaluate(self, spec: str, demonstrations: Sequence[str], candidates: Mapping[str, Sequence[str]],
                 points: Mapping[str, Sequence[Point]] | None = None) -> EvaluateResult: ...


def conjunction(assertions: Sequence[str]) -> str:
    if not assertions:
        return "True"
    if len(assertions) == 1:
        return assertions[0]
    return " and ".join(f"({a})" for a in assertions)


def _chunk_points(points: Sequence[Point], lo: int, hi: int) -> tuple[int, list[Point]]:
    """Points of test trajectories [lo, hi), re-indexed to the chunk; and where they start in `points`.

    Domain points are ordered by trajectory, so a chunk's points are one contiguous slice.
    """
    local = [(k, Point(p.demo - lo, p.position, p.args)) for k, p in enumerate(points) if lo <= p.demo < hi]
    start = local[0][0] if local else 0
    if local and local[-1][0] - start + 1 != len(local):
        raise ValueError("domain points are not ordered by trajectory")
    return start, [p for _, p in local]


class Satisfaction:
    def __init__(self, evaluator: Evaluator, cache: JsonCache, chunk: int = CHUNK_TRAJECTORIES) -> None:
        self.evaluator = evaluator
        self.cache = cache
        self.chunk = chunk

    def bitsets(self, domain: Domain, expressions: Mapping[str, Iterable[str]],
                progress: Progress | None = None) -> dict[str, dict[str, int]]:
        """{action: {expression: C bitset over domain.points[action]}}, computing only what is not cached."""
        known = {a: self._load(domain, a) for a in expressions}
        missing = {a: sorted(set(exprs) - set(known[a])) for a, exprs in expressions.items()}
        missing = {a: e for a, e in missing.items() if e}
        if missing:
            computed = self._compute(domain, missing, progress)
            for action, found in computed.items():
                known[action].update(found)
                stored = {e: format(b, "x") for e, b in known[action].items()}
                self.cache.put(stored, "sat", domain.name, action)
        return {a: {e: known[a][e] for e in exprs} for a, exprs in expressions.items()}

    def _load(self, domain: Domain, action: str) -> dict[str, int]:
        stored = self.cache.get("sat", domain.name, action) or {}
        return {e: int(h, 16) for e, h in stored.items()}

    def _compute(self, domain: Domain, missing: Mapping[str, list[str]],
                 progress: Progress | None) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {a: dict.fromkeys(e, 0) for a, e in missing.items()}
        for lo in range(0, len(domain.test), self.chunk):
            hi = min(lo + self.chunk, len(domain.test))
            starts: dict[str, int] = {}
            points: dict[str, list[Point]] = {}
            for action in missing:
                starts[action], points[action] = _chunk_points(domain.points[action], lo, hi)
            result = self.evaluator.evaluate(domain.spec, domain.test[lo:hi], missing, points)
            for action, judged in result.results.items():
                for candidate in judged:
                    out[action][candidate.expression] |= candidate.satisfied << starts[action]
            if progress:
                progress(hi - lo)
        return out


def score(domain: Domain, preconditions: Mapping[str, Sequence[str]], sat: Satisfaction,
          progress: Progress | None = None) -> dict[str, ActionScore]:
    """Per-action scores of `preconditions` (actions it omits are "always allowed") against the GT."""
    predicted = {a: conjunction(preconditions.get(a, [])) for a in domain.actions}
    truth = {a: conjunction(domain.gt.get(a, [])) for a in domain.actions}
    sets = sat.bitsets(domain, {a: {predicted[a], truth[a]} for a in domain.actions}, progress)
    return {a: score_action(a, len(domain.points[a]), sets[a][predicted[a]], sets[a][truth[a]])
            for a in domain.actions}
