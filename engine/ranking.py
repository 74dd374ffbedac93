"""Choosing preconditions among valid candidates, from their satisfaction sets C_h (bitsets over points).

`subsumption` is the paper's eq. (hopt): keep the clusters whose C_h has no strict subset among the valid
clusters. It is precise but keeps every condition that merely happened to hold at all demonstrated
occurrences (the paper's INFORM example keeps `query_success`), which costs recall.

`recency` is our recall-aware criterion (the default, chosen on the SGD dev numbers in docs/results.md): of
the subsumption-minimal clusters it keeps those that *enabled* at least one occurrence: made true by the
observations since the agent's previous turn, or, for conditions on the action's own arguments, true since
the episode began ("this slot was not informed yet"). Conditions that merely describe the episode's phase
("a search has succeeded", "nothing was selected yet") are dropped.

`marginal` is a simpler recall-aware alternative: minimal clusters, most selective first, each kept only while
it still excludes `MIN_GAIN` of the points that the conjunction so far allows.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from sandbox.types import Point

MIN_GAIN = 0.3
MIN_VOTES = 2


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
    params: tuple[str, ...] = ()


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


def _mentions(expression: str, names: Sequence[str]) -> bool:
    try:
        tree = ast.parse(expression, mode="eval")
    except SyntaxError:
        return False
    return any(isinstance(node, ast.Name) and node.id in names for node in ast.walk(tree))


def enabling_rate(c: Cluster, evidence: ActionEvidence, index: Mapping[Point, int]) -> float:
    """Share of occurrences the condition enabled.

    A condition on the action's own arguments (`requested_slot[slot]`, `inventory == obj`) is about this very
    call, so it always counts, provided the demonstrations call the action with different arguments: with a
    single value the parameter is a constant in disguise, and the condition is judged like a global one.
    A global condition counts at an occurrence only when it was false during the observations since the
    agent's previous turn, i.e. they made it true; otherwise it describes where the episode is (a phase:
    "a search has succeeded", "nothing was selected yet"), which held at the demonstrated occurrences by the
    episodes' usual order rather than by necessity.
    """
    if not evidence.occurrences:
        return 0.0
    varied = len({occ.args for occ in evidence.occurrences}) > 1
    if varied and any(_mentions(m.expression, evidence.params) for m in c.members):
        return 1.0
    enabling = 0
    for occ in evidence.occurrences:
        window = evidence.previous_turn.get((occ.demo, occ.position), 0)
        if _false_between(c, occ, window, index):
            enabling += 1
    return enabling / len(evidence.occurrences)


def recency(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    """Subsumption-minimal clusters that enabled at least one demonstrated occurrence.

    An action none of whose conditions ever enabled it keeps no precondition: what held at its occurrences
    held by the episodes' order, and guessing there costs more recall than it buys precision.
    """
    index = {point: bit for bit, point in enumerate(evidence.points)}
    return [c for c in subsumption(clusters) if enabling_rate(c, evidence, index) > 0]


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


def zero_shot(valid: Sequence[Candidate], votes: Mapping[str, int], params: Sequence[str]) -> list[Cluster]:
    """An action never demonstrated has no evidence to rank by: every candidate is vacuously valid.

    Then the code model's prior is all there is (the paper's zero-shot setting): keep its most-proposed
    assertion about the state or the arguments (`assert False` is a favourite of small models), if more than
    one sample agreed on it.
    """
    names = ("self", *params)
    proposed = [c for c in valid if votes.get(c.expression, 0) >= MIN_VOTES and _mentions(c.expression, names)]
    if not proposed:
        return []
    best = max(proposed, key=lambda c: (votes[c.expression], -len(c.expression)))
    return [Cluster((best,))]


def rank(criterion: str, clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    if criterion == "recency":
        return recency(clusters, evidence)
    if criterion == "marginal":
        return marginal(clusters, evidence)
    return subsumption(clusters)


def _quote(text: str, limit: int = 120) -> str:
    return repr(text if len(text) <= limit else text[: limit - 3] + "...")


def explain(
    criterion: str,
    valid: Sequence[Candidate],
    clusters: Sequence[Cluster],
    chosen: Sequence[Cluster],
    evidence: ActionEvidence,
    votes: Mapping[str, int],
) -> dict[str, str]:
    """In words, why each valid candidate was kept or dropped by clustering and ranking (the sandbox already
    says why an invalid or rejected one failed). Recomputes what the criterion looked at; never decides."""
    n_points = len(evidence.points)
    everything = (1 << n_points) - 1
    reasons: dict[str, str] = {}
    chosen_sets = {c.satisfied for c in chosen}
    if not evidence.occurrences:
        best = chosen[0].representative.expression if chosen else None
        for candidate in valid:
            n = votes.get(candidate.expression, 0)
            if candidate.expression == best:
                reasons[candidate.expression] = (
                    f"zero-shot: never demonstrated, kept by model vote ({n} samples proposed it, the most)")
            elif best is not None:
                reasons[candidate.expression] = (
                    f"zero-shot: never demonstrated; {_quote(best)} had more model votes ({n} here)")
            else:
                reasons[candidate.expression] = (
                    f"zero-shot: never demonstrated, so it holds vacuously; dropped: fewer than {MIN_VOTES} model "
                    f"samples agreed on any assertion about the state or the arguments ({n} here)")
        return reasons
    informative_sets = {c.satisfied for c in clusters}
    minimal = {c.satisfied for c in subsumption(clusters)}
    index = {point: bit for bit, point in enumerate(evidence.points)}
    for candidate in valid:
        mine = candidate.satisfied
        if mine not in informative_sets:
            reasons[candidate.expression] = (
                "held at every demonstrated point, so it excludes nothing: says nothing" if mine == everything
                else "held at no demonstrated point other than where it is vacuous: says nothing")
            continue
        group = next(c for c in clusters if c.satisfied == mine)
        representative = group.representative.expression
        if candidate.expression != representative:
            reasons[candidate.expression] = (
                f"equivalent to {_quote(representative)} on the demonstrations (same cluster); the shortest is kept")
            continue
        if mine not in minimal:
            stronger = min((c for c in clusters if c.satisfied != mine and c.satisfied & ~mine == 0),
                           key=lambda c: (c.satisfied.bit_count(), len(c.representative.expression)))
            reasons[candidate.expression] = (
                f"subsumed by {_quote(stronger.representative.expression)}: that rule also held at every "
                "occurrence and holds at fewer points, so it implies this one")
            continue
        rate = enabling_rate(group, evidence, index)
        if mine in chosen_sets:
            if criterion == "recency":
                reasons[candidate.expression] = (
                    f"kept: held at every occurrence, no valid rule is stricter, and it was made true before "
                    f"{rate:.0%} of the occurrences (or is about the action's own arguments)")
            elif criterion == "marginal":
                reasons[candidate.expression] = (
                    "kept: held at every occurrence, no valid rule is stricter, and it still excluded enough of the "
                    "points the rules before it allowed")
            else:
                reasons[candidate.expression] = (
                    "kept: held at every occurrence and no valid rule is stricter (subsumption-minimal)")
        elif criterion == "recency":
            reasons[candidate.expression] = (
                "held at every occurrence, but was already true before the user's last turn each time: looks "
                "like a phase, not a requirement")
        else:
            reasons[candidate.expression] = (
                f"held at every occurrence, but excluded less than {MIN_GAIN:.0%} of the points the stricter "
                "rules already allowed: likely a coincidence")
    return reasons
