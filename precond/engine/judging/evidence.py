"""How much the demonstrations back a candidate rule, and whether that is enough to keep it.

Real logs come from human agents: a few percent of their steps break the policy, and some actions occur once
or twice. Strict validation (the paper: a rule must hold at every occurrence) turns one slip into a missing
rule and one occurrence into a confident coincidence. Here a rule is judged on its counts instead:

* n occurrences of the action, k of them where the rule holds (n - k exceptions);
* m other points of the same demonstrations (positions x argument tuples), j of them where it holds.

Three tests (docs/method.md, "Evidence-weighted validation"):

1. *Refuted*: exceptions may be at most a share `tolerance` of the occurrences (n - k <= floor(tolerance x n)),
   unless the rule is *strongly separated* (below). Tolerance 0 refutes on the first exception: the paper's
   strict validation, and then nothing below applies.
   (A binomial test of "slips at rate `tolerance`" was measured first: it forgives 3 exceptions in 25 at
   tolerance 0.05, and let correlated coincidences such as REQUEST: `not informed_slot['date']` in.)
   *Strong separation*: a fixed share cannot tell slips from a correlation, because slips concentrate: an
   agent who re-asks a slot always does it with the same action, so errors at 5% of the steps are 10-27% of
   one action's calls. What tells them apart is how strongly the rule singles the calls out from the rest of
   the dialogs, and whether it still does next to the rules already kept. So more exceptions are forgiven
   when (a) holding k of n times at background p0 is far beyond chance, P[Bin(n, p0) >= k] < `STRONG_ALPHA`
   (the chance test of 2. at a level 250 times stricter), (b) the exceptions stay a minority: at most
   `MAX_SLIP_SHARE` of the calls, and the rule allows a majority of them with 95% confidence (`confidence`
   > 1/2, which one exception among 4 or 5 calls fails: `user.no_more` at 3 of 4 REQ_MORE calls, 6% of the
   other points, is not a rule with a slip), and (c) there are other points to be separated from. Then
   `ranking.within_budget` applies the same test to what the rule adds to the rules kept before it (its
   counts among the points they still allow). A correlated condition fails there: Events CONFIRM
   `informed_intent['BuyEventTickets']` (48 of 54 calls, 54% elsewhere) and Homes INFORM
   `requested_slot['pets_allowed']` (17 of 23, 30%) pass (a) and (b) alone, but next to the rules that hold
   at every call (`informed_slot['number_of_seats']`, `requested_slot[slot]`) they separate nothing more.
   A requirement broken by slips is usually the action's only strong rule, and passes: REQUEST
   `not informed_slot[slot]` at 25 of 30 calls, 41% elsewhere, p = 2e-6.
2. *Chance*: a condition that holds at the other points at rate p0 = (j + 1) / (m + 2) holds at k or more of
   n occurrences by chance with probability P[Bin(n, p0) >= k] (one-sided binomial tail, computed with
   `math`); the rule is kept only below `CHANCE_ALPHA`. A condition true almost everywhere says nothing.
3. *Thin*: fewer than `MIN_OCCURRENCES` occurrences, or occurrences in fewer than `MIN_DIALOGS` demonstrations
   (seven failure notices in two dialogs are two situations), never make a rule from evidence (a coincidence at one
   or two calls is indistinguishable from a requirement); the action is treated like a never-demonstrated
   one and its rule comes from the zero-shot path (`ranking.zero_shot`: the model's votes) or is empty.

The kept rules of an action are a conjunction, so their exceptions add up: `ranking.within_budget` keeps the
union of what they refuse within the same share, plus what strongly separated rules are forgiven.

`confidence` is the Wilson lower bound (95%, one-sided) of the share of the action's calls at which the rule
holds: 1 of 1 gives 0.27, 10 of 10 gives 0.79, 40 of 40 gives 0.94, so a caller can tell thin from solid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from precond.sandbox.types import Point
from precond_client.schemas import Verdict

MIN_OCCURRENCES = 3
MIN_DIALOGS = 3
CHANCE_ALPHA = 0.25
STRONG_ALPHA = 1e-3
MAX_SLIP_SHARE = 0.3
CONFIDENCE_Z = 1.645  # one-sided 95%


def binomial_tail(n: int, k: int, p: float) -> float:
    """P[X >= k] for X ~ Bin(n, p), summed over the shorter side in log space (exact for the n of a request)."""
    if k <= 0:
        return 1.0
    if k > n or p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    log_p, log_q = math.log(p), math.log1p(-p)

    def pmf(i: int) -> float:
        return math.exp(math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * log_p
                        + (n - i) * log_q)

    if n - k < k:
        return min(1.0, sum(pmf(i) for i in range(k, n + 1)))
    return max(0.0, 1.0 - sum(pmf(i) for i in range(k)))


def wilson_lower(k: int, n: int, z: float = CONFIDENCE_Z) -> float:
    """Lower bound of a binomial proportion; 0 without trials (no evidence, no confidence)."""
    if n == 0:
        return 0.0
    share = k / n
    centre = share + z * z / (2 * n)
    spread = z * math.sqrt(share * (1 - share) / n + z * z / (4 * n * n))
    return max(0.0, (centre - spread) / (1 + z * z / n))


@dataclass(frozen=True)
class OccurrenceIndex:
    """An action's occurrences as bits of its point list, computed once per action, reused per candidate."""

    occurrences: tuple[Point, ...]
    bits: tuple[int | None, ...]  # None: the occurrence is not among the points (never holds)
    mask: int
    n_points: int

    @classmethod
    def of(cls, points: Sequence[Point], occurrences: Sequence[Point]) -> OccurrenceIndex:
        distinct = tuple(dict.fromkeys(occurrences))
        bits = tuple(_bit(points, occ) for occ in distinct)
        mask = 0
        for bit in bits:
            if bit is not None:
                mask |= 1 << bit
        return cls(distinct, bits, mask, len(points))


def _bit(points: Sequence[Point], occ: Point) -> int | None:
    try:
        return points.index(occ)
    except ValueError:
        return None


@dataclass(frozen=True)
class Evidence:
    """Counts behind one candidate: where it holds among the occurrences and among the other points."""

    occurrences: int
    holds: int
    elsewhere: int
    holds_elsewhere: int
    satisfied: int = field(default=0, repr=False)
    index: OccurrenceIndex | None = field(default=None, repr=False, compare=False)

    @property
    def exceptions(self) -> tuple[Point, ...]:
        """The occurrences it refuses; computed on demand (most candidates are refuted and never listed)."""
        if self.index is None or self.holds == self.occurrences:
            return ()
        return tuple(occ for occ, bit in zip(self.index.occurrences, self.index.bits, strict=True)
                     if bit is None or not (self.satisfied >> bit) & 1)

    @property
    def confidence(self) -> float:
        return wilson_lower(self.holds, self.occurrences)

    @property
    def background(self) -> float:
        """The rate at which it holds where the action was not taken, smoothed so that 0 of 0 is 1/2."""
        return (self.holds_elsewhere + 1) / (self.elsewhere + 2)

    def chance(self) -> float:
        """P-value of holding this often at the occurrences if they were points like the others."""
        return binomial_tail(self.occurrences, self.holds, self.background)


def gather(satisfied: int, index: OccurrenceIndex) -> Evidence:
    holds = (satisfied & index.mask).bit_count()
    elsewhere = index.n_points - index.mask.bit_count()
    return Evidence(len(index.occurrences), holds, elsewhere, satisfied.bit_count() - holds, satisfied, index)


def strongly_separated(evidence: Evidence) -> bool:
    """Exceptions beyond the tolerance are forgiven when the rule separates the occurrences from the other
    points so clearly that holding this often is no chance, and they stay a minority of the calls."""
    exceptions = evidence.occurrences - evidence.holds
    return (evidence.elsewhere > 0 and exceptions <= MAX_SLIP_SHARE * evidence.occurrences
            and evidence.confidence > 0.5 and evidence.chance() < STRONG_ALPHA)


def strict(tolerance: float) -> bool:
    """Tolerance 0 is the paper's strict validation: a rule must hold at every demonstrated call, and nothing
    of the evidence weighting below applies."""
    return tolerance <= 0


def exception_budget(tolerance: float, occurrences: int) -> int:
    """The demonstrated calls a rule (or the rules of one action together) may refuse at this tolerance."""
    return math.floor(tolerance * occurrences + 1e-9)


def verdict(evidence: Evidence, tolerance: float) -> Verdict:
    """Whether the evidence backs the rule; tolerance 0 is the paper's strict validation and nothing more."""
    exceptions = evidence.occurrences - evidence.holds
    if strict(tolerance):
        return "refuted" if exceptions else "held"
    if exceptions > exception_budget(tolerance, evidence.occurrences) and not strongly_separated(evidence):
        return "refuted"
    if evidence.occurrences < MIN_OCCURRENCES:
        return "thin"
    if evidence.chance() >= CHANCE_ALPHA:
        return "chance"
    return "tolerated" if exceptions else "held"


def too_few(occurrences: Sequence[Point]) -> bool:
    """Fewer than MIN_OCCURRENCES calls, or all of them in fewer than MIN_DIALOGS demonstrations: calls in one
    dialog share its situation, so they are not independent evidence."""
    distinct = set(occurrences)
    return len(distinct) < MIN_OCCURRENCES or len({point.demo for point in distinct}) < MIN_DIALOGS


def thin(occurrences: Sequence[Point], tolerance: float) -> bool:
    """Demonstrated, but too thinly to learn from (only with evidence weighting on: tolerance > 0)."""
    return not strict(tolerance) and bool(occurrences) and too_few(occurrences)


def describe(evidence: Evidence, lines: Sequence[str] = ()) -> str:
    """The counts in words, as reasons cite them; `lines` name the exceptions ('demonstration 3, line 12')."""
    listed = "; ".join(lines[:3]) + ("; ..." if len(lines) > 3 else "")
    where = f" (exceptions: {listed})" if lines else ""
    share = evidence.holds_elsewhere / evidence.elsewhere if evidence.elsewhere else 0.0
    return (f"held at {evidence.holds} of {evidence.occurrences} occurrences{where} and at {share:.0%} of the "
            f"other points; confidence {evidence.confidence:.2f}")
