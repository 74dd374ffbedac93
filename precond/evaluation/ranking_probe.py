"""A measurement, not a feature: how much F1 a discriminativeness cut in the ranking would buy.

`engine.ranking.informative` drops clusters that hold at *every* demonstration point; subsumption then keeps
every minimal cluster. With the enumerator's thousands of atoms, many minimal clusters are conditions that
hold almost everywhere in the demonstrations (`not self.user.requested_slot['price_range']`,
`self.query_success is not None`) and were true at every occurrence by accident. Each one is conjoined
into the precondition and costs recall on the test dialogs while buying almost no precision.

This probe re-ranks the engine's own valid candidates with one extra rule, "drop clusters true at more than
`max_rate` of the demonstration points", then applies the engine's ranking (subsumption or recency) unchanged,
and scores the result like any other configuration (config key `maxrate=`, see precond/evaluation/configs.py).
It works from the valid candidates cached with an inference, so model configurations are re-ranked without
generating again; candidates run in the sandbox only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from precond.engine.judging.ranking import ActionEvidence, Candidate, Cluster, cluster, rank
from precond.engine.judging.selection import previous_turns  # the engine's own evidence, so only the new rule differs
from precond.evaluation.domains import Domain
from precond.sandbox import Sandbox


def discriminative(clusters: Sequence[Cluster], n_points: int, max_rate: float) -> list[Cluster]:
    return [c for c in clusters if 0 < c.satisfied.bit_count() <= max_rate * n_points]


def rerank(domain: Domain, demonstrations: Sequence[str], valid: Mapping[str, Sequence[str]],
           sandbox: Sandbox, ranking: str, max_rate: float) -> dict[str, list[str]]:
    valid = {a: list(valid.get(a, ())) for a in domain.actions}
    trace = sandbox.trace(domain.spec, demonstrations)
    evaluated = sandbox.evaluate(domain.spec, demonstrations, valid)
    turns = previous_turns(trace)
    out: dict[str, list[str]] = {}
    for action in domain.actions:
        points = evaluated.points.get(action, ())
        candidates = [Candidate(r.expression, "probe", r.satisfied)
                      for r in evaluated.results.get(action, ()) if r.status == "valid"]
        occurrences = trace.actions[action].occurrences
        kept = discriminative(cluster(candidates), len(points), max_rate)
        chosen = rank(ranking, kept, ActionEvidence(points, occurrences, turns)) if occurrences else []
        out[action] = [c.representative.expression for c in chosen]
    return out
