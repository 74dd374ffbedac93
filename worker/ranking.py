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
MIN_GAIN = 0.3


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
    previous_turn: Mapping[tuple[int, int], int]  # (demo, position) -> first observation since the agent's last turn


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


def _false_between(c: Cluster, occ: Point, start: int, index: Mapping[Point, int]) -> bool:
    for position in range(start, occ.position):
        bit = index.get(Point(occ.demo, position, occ.args))
        if bit is not None and not (c.satisfied >> bit) & 1:
            return True
    return False


def enabling_rate(c: Cluster, evidence: ActionEvidence, index: Mapping[Point, int]) -> float:
    """Share of occurrences where the condition is not a mere phase.

    At an occurrence a condition is a *phase* when it was false at some point earlier in the demonstration
    but already true throughout the observations since the agent's previous turn. It is *enabling* when it
    was false during those observations (they made it true), or *invariant* when it was never false before
    (e.g. "the slot was not informed yet").
    """
    if not evidence.occurrences:
        return 0.0
    enabling = 0
    for occ in evidence.occurrences:
        window = evidence.previous_turn.get((occ.demo, occ.position), 0)
        if _false_between(c, occ, window, index) or not _false_between(c, occ, 0, index):
            enabling += 1
    return enabling / len(evidence.occurrences)


def recency(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    minimal = subsumption(clusters)
    index = {point: bit for bit, point in enumerate(evidence.points)}
    enabling = [c for c in minimal if enabling_rate(c, evidence, index) >= RECENCY_THRESHOLD]
    return marginal(enabling, evidence) or marginal(minimal, evidence)


def marginal(clusters: Sequence[Cluster], evidence: ActionEvidence, min_gain: float = MIN_GAIN) -> list[Cluster]:
    """Subsumption-minimal clusters, added most-selective first while each still excludes at least
    `min_gain` of the points that the conjunction so far allows.

    A condition that only trims a few more points off an already tight conjunction is the kind that held at
    every demonstrated occurrence by coincidence (`not requested_slot['price_range']`); leaving it out buys
    recall on unseen dialogs for little precision.
    """
    remaining = list(subsumption(clusters))
    allowed = (1 << len(evidence.points)) - 1
    chosen: list[Cluster] = []
    while remaining:
        best = min(remaining, key=lambda c: ((allowed & c.satisfied).bit_count(), len(c.representative.expression)))
        gain = 1 - (allowed & best.satisfied).bit_count() / max(allowed.bit_count(), 1)
        if gain < min_gain:
            break
        chosen.append(best)
        allowed &= best.satisfied
        remaining.remove(best)
    return chosen


def rank(criterion: str, clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    if criterion == "recency":
        return recency(clusters, evidence)
    if criterion == "marginal":
        return marginal(clusters, evidence)
    return subsumption(clusters)
