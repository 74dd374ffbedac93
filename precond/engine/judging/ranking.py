"""Choosing preconditions among valid candidates, from their satisfaction sets C_h (bitsets over points).

`subsumption` is the paper's eq. (hopt): keep the clusters whose C_h has no strict subset among the valid
clusters. It is precise but keeps every condition that merely happened to hold at all demonstrated
occurrences (the paper's INFORM example keeps `query_success`), which costs recall.

`recency` is our recall-aware criterion (the default, chosen on the SGD dev numbers in docs/results.md): of
the subsumption-minimal clusters it keeps those that *enabled* at least one occurrence: made true by the
observations since the agent's previous turn, or, for conditions on the action's own arguments, true since
the episode began ("this slot was not informed yet"). Conditions that merely describe the episode's phase
("a search has succeeded", "nothing was selected yet") are dropped.

With evidence-weighted validation (precond/engine/judging/evidence.py) a kept candidate may have exceptions, so
subsumption
compares only rules that agree on the demonstrated calls: a rule that is stricter by refusing calls another
allows is not "more specific", it is contradicted more often (`ActionEvidence.occurrence_mask`). Under strict
validation every valid rule holds at every occurrence, and this is the paper's eq. (hopt) unchanged.

`marginal` is a simpler recall-aware alternative: minimal clusters, most selective first, each kept only while
it still excludes `MIN_GAIN` of the points that the conjunction so far allows.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from precond.engine.judging.evidence import Evidence, exception_budget, strict, strongly_separated
from precond.engine.judging.freshness import Access, reads, refreshed
from precond.sandbox.types import Point

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
    occurrence_mask: int = 0  # the occurrences' bits among `points`
    thin: bool = False  # too few occurrences to learn from: ranked like a never-demonstrated action
    tolerance: float = 0.0  # share of the occurrences the kept rules together may refuse
    writes: Mapping[tuple[int, int], frozenset[Access]] = field(default_factory=dict)  # what observations wrote
    confirmed: Mapping[tuple[int, int], frozenset[str]] = field(default_factory=dict)  # what the turn before asked
    slots: frozenset[str] = frozenset()  # every slot the agent's acts name (`selection.confirmations`)


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


def subsumption(clusters: Sequence[Cluster], occurrence_mask: int = 0) -> list[Cluster]:
    """Eq. (hopt): no other valid cluster's C_h is a strict subset of this one's, among those that allow every
    occurrence this one allows (all of them under strict validation)."""
    sets = [c.satisfied for c in clusters]
    return [c for c, mine in zip(clusters, sets, strict=True)
            if not any(_stricter(other, mine, occurrence_mask) for other in sets)]


def _stricter(other: int, mine: int, occurrence_mask: int) -> bool:
    return other != mine and other & ~mine == 0 and mine & ~other & occurrence_mask == 0


def _false_between(c: Cluster, occ: Point, start: int, index: Mapping[Point, int]) -> bool:
    for position in range(start, occ.position):
        bit = index.get(Point(occ.demo, position, occ.args))
        if bit is not None and not (c.satisfied >> bit) & 1:
            return True
    return False


def _holds_at(c: Cluster, occ: Point, index: Mapping[Point, int]) -> bool:
    bit = index.get(occ)
    return bit is not None and bool((c.satisfied >> bit) & 1)


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

    With `evidence.writes` (the cautious criterion, precond/engine/judging/freshness.py) an observation that wrote the
    very
    state the condition reads *renews* it (a second "success" before a success notice); renewals count when
    they, with the occurrences it was made true at, are at least half of the occurrences: a condition renewed
    now and then by chance (a "no" that re-set a flag already unset) stays a phase.
    """
    if not evidence.occurrences:
        return 0.0
    if _about_arguments(c, evidence):
        return 1.0
    fates = enabled_at(c, evidence, index)
    made, renewed = fates.count("made"), fates.count("renewed")
    n = len(evidence.occurrences)
    return made / n if made or (made + renewed) * 2 < n else (made + renewed) / n


def _about_arguments(c: Cluster, evidence: ActionEvidence) -> bool:
    varied = len({occ.args for occ in evidence.occurrences}) > 1
    return varied and any(_mentions(m.expression, evidence.params) for m in c.members)


def enabled_at(c: Cluster, evidence: ActionEvidence, index: Mapping[Point, int]) -> list[str | None]:
    """Per occurrence: "made" (false since the agent's previous turn, true at the call), "renewed" (written
    again by an observation since then) or None (held already, or not at all)."""
    read = reads(c.representative.expression) if evidence.writes else frozenset()
    fates: list[str | None] = []
    for occ in evidence.occurrences:
        window = evidence.previous_turn.get((occ.demo, occ.position), 0)
        if not _holds_at(c, occ, index):  # a tolerated exception: the condition enabled nothing there
            fates.append(None)
        elif _false_between(c, occ, window, index):
            fates.append("made")
        elif read and refreshed(read, occ, window, evidence.writes):
            fates.append("renewed")
        else:
            fates.append(None)
    return fates


def recency(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    """Subsumption-minimal clusters that enabled at least one demonstrated occurrence.

    An action none of whose conditions ever enabled it keeps no precondition: what held at its occurrences
    held by the episodes' order, and guessing there costs more recall than it buys precision.
    """
    index = {point: bit for bit, point in enumerate(evidence.points)}
    return [c for c in subsumption(clusters, evidence.occurrence_mask) if enabling_rate(c, evidence, index) > 0]


def marginal(clusters: Sequence[Cluster], evidence: ActionEvidence, min_gain: float = MIN_GAIN) -> list[Cluster]:
    """Subsumption-minimal clusters, added most-selective first while each still excludes at least
    `min_gain` of the points that the conjunction so far allows.

    A condition that only trims a few more points off an already tight conjunction is the kind that held at
    every demonstrated occurrence by coincidence (`not requested_slot['price_range']`); leaving it out buys
    recall on unseen dialogs for little precision.
    """
    remaining = list(subsumption(clusters, evidence.occurrence_mask))
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
    return within_budget(by_criterion(criterion, clusters, evidence), evidence)


def by_criterion(criterion: str, clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    if criterion == "recency":
        return recency(clusters, evidence)
    if criterion == "marginal":
        return marginal(clusters, evidence)
    return subsumption(clusters, evidence.occurrence_mask)


def action_budget(evidence: ActionEvidence) -> int:
    """The calls of the action that its chosen rules together may refuse."""
    return exception_budget(evidence.tolerance, evidence.occurrence_mask.bit_count())


def within_budget(chosen: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    """The chosen rules whose exceptions, together, stay within the tolerance: the precondition is their
    conjunction, so what it refuses is the union of what each refuses.

    Rules that held everywhere come first, then the fewest exceptions; a rule whose exceptions would push the
    union over the budget is left out, unless it strongly separates the occurrences the rules kept before it
    still allow from the other points they allow (`evidence.strongly_separated` on those counts).
    """
    mask = evidence.occurrence_mask
    if strict(evidence.tolerance) or not mask:
        return list(chosen)
    everything = (1 << len(evidence.points)) - 1
    budget, charged, allowed, kept = action_budget(evidence), 0, everything, set()
    for c in sorted(chosen, key=lambda c: (mask & ~c.satisfied).bit_count()):
        new = (mask & allowed & ~c.satisfied).bit_count()
        if charged + new <= budget:
            charged += new
        elif not strongly_separated(_given(c.satisfied, allowed, mask, everything)):
            continue
        kept.add(c.satisfied)
        allowed &= c.satisfied
    return [c for c in chosen if c.satisfied in kept]


def _given(satisfied: int, allowed: int, mask: int, everything: int) -> Evidence:
    """A rule's counts among the points the rules kept so far allow: what it adds to their conjunction."""
    occurrences, others = mask & allowed, everything & ~mask & allowed
    return Evidence(occurrences.bit_count(), (occurrences & satisfied).bit_count(), others.bit_count(),
                    (others & satisfied).bit_count())


def _held(satisfied: int, evidence: ActionEvidence) -> str:
    refused = (evidence.occurrence_mask & ~satisfied).bit_count()
    if not refused:
        return "held at every occurrence"
    if refused <= action_budget(evidence):
        return "held at the occurrences within the tolerance"
    return "held at most occurrences (more exceptions than the tolerance, forgiven for its strong separation)"


def _quote(text: str, limit: int = 120) -> str:
    return repr(text if len(text) <= limit else text[: limit - 3] + "...")


def explain(
    criterion: str,
    valid: Sequence[Candidate],
    clusters: Sequence[Cluster],
    chosen: Sequence[Cluster],
    evidence: ActionEvidence,
    votes: Mapping[str, int],
    over_budget: Sequence[Cluster] = (),
) -> dict[str, str]:
    """In words, why each valid candidate was kept or dropped by clustering and ranking (the sandbox already
    says why an invalid or rejected one failed). Recomputes what the criterion looked at; never decides.
    `over_budget`: what the criterion chose and `within_budget` left out."""
    n_points = len(evidence.points)
    everything = (1 << n_points) - 1
    reasons: dict[str, str] = {}
    chosen_sets = {c.satisfied for c in chosen}
    if not evidence.occurrences or evidence.thin:
        return _explain_zero_shot(valid, chosen, evidence, votes)
    informative_sets = {c.satisfied for c in clusters}
    mask = evidence.occurrence_mask
    minimal = {c.satisfied for c in subsumption(clusters, mask)}
    cut = {c.satisfied for c in over_budget}
    index = {point: bit for bit, point in enumerate(evidence.points)}
    for candidate in valid:
        mine = candidate.satisfied
        held = _held(mine, evidence)
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
            stronger = min((c for c in clusters if _stricter(c.satisfied, mine, mask)),
                           key=lambda c: (c.satisfied.bit_count(), len(c.representative.expression)))
            reasons[candidate.expression] = (
                f"subsumed by {_quote(stronger.representative.expression)}: that rule also held at every "
                "occurrence this one held at, and holds at fewer points, so it implies this one")
            continue
        rate = enabling_rate(group, evidence, index)
        if mine in cut:
            reasons[candidate.expression] = (
                f"{held}, but its exceptions together with those of the rules kept before it exceed the "
                f"tolerance ({action_budget(evidence)} of {mask.bit_count()} occurrences), and among the "
                "points those rules still allow it does not single the occurrences out strongly")
            continue
        reasons[candidate.expression] = _ranked(criterion, held, rate, mine in chosen_sets)
    return reasons


def _ranked(criterion: str, held: str, rate: float, kept: bool) -> str:
    """Why a minimal, informative rule within the tolerance was kept or passed over by the criterion."""
    if kept:
        if criterion in ("recency", "cautious"):
            return (f"kept: {held}, no valid rule is stricter, and it was made true before "
                    f"{rate:.0%} of the occurrences (or is about the action's own arguments)")
        if criterion == "marginal":
            return (f"kept: {held}, no valid rule is stricter, and it still excluded enough of the "
                    "points the rules before it allowed")
        return f"kept: {held} and no valid rule is stricter (subsumption-minimal)"
    if criterion in ("recency", "cautious"):
        return (f"{held}, but was already true before the user's last turn each time: looks like a phase, "
                "not a requirement")
    return (f"{held}, but excluded less than {MIN_GAIN:.0%} of the points the stricter "
            "rules already allowed: likely a coincidence")


def _explain_zero_shot(valid: Sequence[Candidate], chosen: Sequence[Cluster], evidence: ActionEvidence,
                       votes: Mapping[str, int]) -> dict[str, str]:
    """Never demonstrated, or too thinly to learn from: the model's votes decide, or nothing is kept."""
    n_occ = len(evidence.occurrences)
    why = ("never demonstrated" if not n_occ else
           f"only {n_occ} occurrence{'s' if n_occ > 1 else ''}, too few to tell a rule from a coincidence")
    vacuous = ", so it holds vacuously" if not n_occ else ""
    best = chosen[0].representative.expression if chosen else None
    reasons: dict[str, str] = {}
    for candidate in valid:
        n = votes.get(candidate.expression, 0)
        if candidate.expression == best:
            reasons[candidate.expression] = f"zero-shot: {why}, kept by model vote ({n} samples proposed it, the most)"
        elif best is not None:
            reasons[candidate.expression] = f"zero-shot: {why}; {_quote(best)} had more model votes ({n} here)"
        else:
            reasons[candidate.expression] = (
                f"zero-shot: {why}{vacuous}; dropped: fewer than {MIN_VOTES} model samples agreed on any assertion "
                f"about the state or the arguments ({n} here)")
    return reasons
