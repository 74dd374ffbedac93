"""Choosing preconditions among valid candidates, from their satisfaction sets C_h (bitsets over points).

`subsumption` is the paper's eq. (hopt): keep the clusters whose C_h has no strict subset among the valid
clusters. It is precise but keeps every condition that merely happened to hold at all demonstrated
occurrences (the paper's INFORM example keeps `query_success`), which costs recall.

`recency` is our recall-aware alternative: among the subsumption-minimal clusters it keeps those whose truth
was *made* true by what happened since the agent last acted (false at some point after its previous action,
true at the action), i.e. conditions that enable the action rather than describe the dialog's phase. When no
cluster shows that pattern for an action it falls back to subsumption, so precision never drops to nothing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from sandbox.types import Point

RECENCY_THRESHOLD = 0.5


@dataclass(frozen=True)
class Candidate:
    expression: str
    source: str
    satisfied: int


@dataclass(frozen=True)
class Cluster:
    members: tuple[Candidate, ...]

    @property
    def satisfied(self) -> int:
        return self.members[0].satisfied

    @property
    def representative(self) -> Candidate:
        """Deterministic stand-in for the paper's random pick: the shortest text, then the first proposed."""
        return min(self.members, key=lambda c: len(c.expression))


@dataclass(frozen=True)
class ActionEvidence:
    """What the ranking needs to know about one action besides the candidates."""

    points: Sequence[Point]
    occurrences: Sequence[Point]
    previous_turn: Mapping[tuple[int, int], int]  # (demo, position) -> position of the agent's last action


def cluster(valid: Sequence[Candidate]) -> list[Cluster]:
    """Candidates with equal satisfaction sets are equivalent on the evidence; clusters keep proposal order."""
    groups: dict[int, list[Candidate]] = {}
    for candidate in valid:
        groups.setdefault(candidate.satisfied, []).append(candidate)
    return [Cluster(tuple(members)) for members in groups.values()]


def informative(clusters: Sequence[Cluster], n_points: int) -> list[Cluster]:
    """Drop clusters true everywhere (`assert True` says nothing) or nowhere (only valid without occurrences)."""
    everything = (1 << n_points) - 1
    return [c for c in clusters if 0 != c.satisfied != everything]


def subsumption(clusters: Sequence[Cluster]) -> list[Cluster]:
    """Eq. (hopt): no other valid cluster's C_h is a strict subset of this one's."""
    sets = [c.satisfied for c in clusters]
    return [
        c
        for c, mine in zip(clusters, sets, strict=True)
        if not any(other != mine and other & ~mine == 0 for other in sets)
    ]


def trigger_rate(c: Cluster, evidence: ActionEvidence, index: Mapping[Point, int]) -> float:
    """Share of occurrences at which the condition was false somewhere since the agent's previous action."""
    if not evidence.occurrences:
        return 0.0
    triggered = 0
    for occ in evidence.occurrences:
        start = evidence.previous_turn.get((occ.demo, occ.position), 0)
        for position in range(start, occ.position):
            bit = index.get(Point(occ.demo, position, occ.args))
            if bit is not None and not (c.satisfied >> bit) & 1:
                triggered += 1
                break
    return triggered / len(evidence.occurrences)


def recency(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    minimal = subsumption(clusters)
    index = {point: bit for bit, point in enumerate(evidence.points)}
    enabling = [c for c in minimal if trigger_rate(c, evidence, index) >= RECENCY_THRESHOLD]
    return enabling or minimal


def rank(criterion: str, clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    if criterion == "recency":
        return recency(clusters, evidence)
    return subsumption(clusters)
