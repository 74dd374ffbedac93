"""What an inference reports about its candidates: every candidate's fate in words, the evidence of the kept
rules (with the demonstrated calls they refuse), and the counts of each stage, built in one place from what
the engine's phases returned (`engine.engine`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from precond.engine.judging.evidence import Evidence, describe
from precond.engine.judging.ranking import Candidate, Cluster
from precond.sandbox.types import CandidateResult, Point, TraceResult
from precond_client.schemas import (
    MAX_CALL_CHARS,
    MAX_LISTED_EXCEPTIONS,
    CandidateReport,
    Decided,
    InferStats,
    Listed,
    RuleEvidence,
    RuleException,
    StageCounts,
    Verdict,
)

UNSEEN_RULE = "False"  # `options.unseen: "refuse"`: a never-demonstrated action is refused until a rule exists


@dataclass
class Proposals:
    """Candidate expressions per action with where they came from, deduplicated across generators."""

    source: dict[str, dict[str, str]] = field(default_factory=dict)
    votes: dict[str, dict[str, int]] = field(default_factory=dict)
    sampled: dict[str, int] = field(default_factory=dict)

    def add(
        self, action: str, expressions: Sequence[str], origin: str, sampled: int, votes: dict[str, int] | None = None
    ) -> None:
        known = self.source.setdefault(action, {})
        self.sampled[action] = self.sampled.get(action, 0) + sampled
        for expression in expressions:
            known.setdefault(expression, origin)
        tally = self.votes.setdefault(action, {})
        for expression, n in (votes or {}).items():
            tally[expression] = tally.get(expression, 0) + n


@dataclass(frozen=True)
class Ranked:
    """One action's candidates after validation and ranking: data that reports and counts are built from."""

    results: Sequence[CandidateResult]
    valid: list[Candidate]
    clusters: list[Cluster]
    chosen: list[Cluster]
    reasons: Mapping[str, str] = field(default_factory=dict)
    """Why ranking kept or dropped each valid candidate (`ranking.explain`), and why evidence-weighted
    validation refuted the others (`_screened`)."""
    evidence: Mapping[str, Evidence] = field(default_factory=dict)
    verdicts: Mapping[str, Verdict] = field(default_factory=dict)
    decided: Mapping[str, Decided] = field(default_factory=dict)
    """How each chosen rule was decided (`engine.cautious.Choice`), by its expression."""
    transferred: Mapping[str, str] = field(default_factory=dict)
    """The sources of each chosen rule transferred from the priors (`engine.priors`), by its expression."""
    search: str = ""
    """Where the disjunction search stopped at its bound (`engine.cautious.MAX_DISJUNCTION_ATOMS`), in words."""
    unguarded: str = ""
    """The assumed rules a conversational act (not in `options.guarded`) did not keep, in words."""
    behind: str = ""
    """The other party's facts a tool call did not keep because its "yes" came before every call, in words."""
    assumed: str = ""
    """The conditions a never-demonstrated action assumed from the other guarded actions (`unseen_shared`), or
    why it assumed none although they share some, in words."""


@dataclass(frozen=True)
class InferenceReport:
    candidates: dict[str, list[CandidateReport]]
    stats: InferStats
    evidence: dict[str, dict[str, RuleEvidence]]


def report_of(
    actions: Sequence[str],
    proposals: Proposals,
    ranked: Mapping[str, Ranked],
    preconditions: Mapping[str, Sequence[str]],
    dropped: Mapping[str, Mapping[str, str]],
    seconds: dict[str, float],
    trace: TraceResult,
) -> InferenceReport:
    """Candidate reports, stage counts and kept rules' evidence of an inference, built in one place from what
    the phases returned."""
    candidates: dict[str, list[CandidateReport]] = {}
    counts: dict[str, StageCounts] = {}
    evidence: dict[str, dict[str, RuleEvidence]] = {}
    for action in actions:
        r = ranked[action]
        origins = proposals.source.get(action, {})
        candidates[action] = _reports(r, origins, preconditions[action], dropped.get(action, {}), trace)
        reports = {c.assertion: c.evidence for c in candidates[action]}
        evidence[action] = {rule: found for rule in preconditions[action] if (found := reports.get(rule))}
        counts[action] = StageCounts(
            sampled=proposals.sampled.get(action, 0), parsed=len(origins), valid=len(r.valid),
            clusters=len(r.clusters), kept=len(preconditions[action]),
        )
    total = StageCounts(**{
        name: sum(getattr(c, name) for c in counts.values()) for name in StageCounts.model_fields
    })
    return InferenceReport(candidates, InferStats(actions=counts, total=total, seconds=seconds), evidence)


def listed(candidates: dict[str, list[CandidateReport]], which: Listed) -> dict[str, list[CandidateReport]]:
    """The candidate reports the caller asked for (`options.candidates`): all, the kept rules' only, or none."""
    if which == "all":
        return candidates
    return {a: [c for c in reports if c.kept] for a, reports in candidates.items()} if which == "kept" else {}


def _reports(
    ranked: Ranked, origins: dict[str, str], kept: Sequence[str], dropped: Mapping[str, str], trace: TraceResult
) -> list[CandidateReport]:
    cluster_of = {m.expression: i for i, c in enumerate(ranked.clusters) for m in c.members}
    valid = {c.expression for c in ranked.valid}
    reports = []
    for result in ranked.results:
        found = ranked.evidence.get(result.expression)
        fate = ranked.verdicts.get(result.expression)
        evidence = None if found is None or fate is None else _rule_evidence(found, fate, trace)
        reason = _reason(result, ranked.reasons, dropped)
        if evidence is not None and fate in ("held", "tolerated") and found is not None and found.occurrences:
            reason = f"{reason}; {describe(found, [_where(x) for x in evidence.exceptions])}"
        is_kept = result.expression in kept
        if evidence is not None and is_kept:
            evidence = evidence.model_copy(update={"decided": ranked.decided.get(result.expression, "established"),
                                                   "source": ranked.transferred.get(result.expression)})
        origin = origins.get(result.expression)
        reports.append(CandidateReport(
            assertion=result.expression,
            source="enumerate" if origin == "enumerate" else "prior" if origin == "prior" else "model",
            valid=is_kept or (result.expression in valid and fate in ("held", "tolerated")),
            cluster=cluster_of.get(result.expression),
            support=result.satisfied.bit_count(),
            kept=is_kept,
            reason=reason,
            evidence=evidence,
        ))
    if UNSEEN_RULE in kept and not any(r.expression == UNSEEN_RULE for r in ranked.results):
        reports.append(_unseen_report())
    return reports


def _unseen_report() -> CandidateReport:
    return CandidateReport(
        assertion=UNSEEN_RULE, source="enumerate", valid=True, support=0, kept=True,
        reason="kept: no demonstration calls this action, no prior rule applies, the code model kept no zero-shot "
               "guess, and options.unseen is 'refuse': every call is refused until a rule is written (or learned "
               "from demonstrations that show it)",
        evidence=RuleEvidence(occurrences=0, holds=0, confidence=0.0, verdict="thin", decided="unseen"),
    )


def _rule_evidence(evidence: Evidence, fate: Verdict, trace: TraceResult) -> RuleEvidence:
    """The API's form; exceptions are listed only for rules that passed validation (a refuted candidate can
    fail at hundreds of calls, and its count says enough)."""
    listed = evidence.exceptions[:MAX_LISTED_EXCEPTIONS] if fate in ("held", "tolerated") else ()
    return RuleEvidence(
        occurrences=evidence.occurrences, holds=evidence.holds, exceptions=[_exception(p, trace) for p in listed],
        elsewhere=evidence.elsewhere, holds_elsewhere=evidence.holds_elsewhere,
        confidence=round(evidence.confidence, 4), verdict=fate,
    )


def _exception(point: Point, trace: TraceResult) -> RuleException:
    steps = trace.positions[point.demo] if 0 <= point.demo < len(trace.positions) else ()
    step = steps[point.position] if 0 <= point.position < len(steps) else None
    return RuleException(demonstration=point.demo, position=point.position,
                         line=step.line if step else None,
                         call=step.source.strip()[:MAX_CALL_CHARS] if step else None)


def _where(exception: RuleException) -> str:
    return f"demonstrations[{exception.demonstration}], line {exception.line}"


def _reason(result: CandidateResult, ranked: Mapping[str, str], dropped: Mapping[str, str]) -> str:
    """Every candidate's fate in words: dropped at verification, rejected by the sandbox, ranked or screened
    (evidence-weighted validation), or violated (strict validation)."""
    if result.expression in dropped:
        return dropped[result.expression]
    if result.status == "rejected":
        return f"rejected before judging: {result.reason or 'unknown reason'}"
    if result.expression in ranked:
        return ranked[result.expression]
    if result.status == "invalid":
        return f"violated at {result.reason}" if result.reason else "violated at a demonstrated occurrence"
    return "valid, but not considered by the ranking"
