"""Each action's rules from its judged candidates: the verdict of each candidate on the evidence, the ranking
criterion's choice (or the zero-shot one for an action too thinly demonstrated), the priors' and the composed
rules, and why each candidate was kept or dropped, as the report shows it.

The sandbox has judged every candidate at every point (`EvaluateResult`); nothing here runs untrusted code.
The request's options travel as one object (`InferOptions`): the criterion, the tolerance and what strict
validation means are read from it here and nowhere else in the engine.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from precond.engine.candidates.tool_relations import labels_only
from precond.engine.judging import categorical, cautious, priors
from precond.engine.judging import guarded as guarding
from precond.engine.judging.evidence import Evidence, OccurrenceIndex, describe, gather, strict, thin, too_few, verdict
from precond.engine.judging.freshness import Access
from precond.engine.judging.ranking import (
    ActionEvidence,
    Candidate,
    Cluster,
    by_criterion,
    cluster,
    explain,
    informative,
    within_budget,
    zero_shot,
)
from precond.engine.judging.report import Proposals, Ranked
from precond.sandbox.types import ActionInfo, CandidateResult, EvaluateResult, TraceResult
from precond_client.schemas import Decided, InferOptions, Verdict


@dataclass(frozen=True)
class Inference:
    """What every action's selection reads: the traced demonstrations, the sandbox's judgments, where each
    candidate came from, the request's options and the state writes (`engine.freshness`, cautious only)."""

    trace: TraceResult
    evaluated: EvaluateResult
    proposals: Proposals
    options: InferOptions
    writes: Mapping[tuple[int, int], frozenset[Access]]
    prior: priors.Priors | None = None


def select_rules(actions: Sequence[str], inference: Inference, guarded: Sequence[str] | None = None
                 ) -> dict[str, Ranked]:
    """`guarded`: the actions whose refusal protects something (engine.guarded); None: every action (the
    cautious criterion alike for all)."""
    turns = previous_turns(inference.trace)
    asked, slots = confirmations(inference.trace, turns) if inference.options.ranking == "cautious" \
        else ({}, frozenset())
    tool_calls = _tool_calls(inference.trace) if inference.options.ranking == "cautious" else set()
    shielded = set(actions if guarded is None else guarded)
    return {action: _select(action, inference, turns, action in tool_calls, action not in shielded,
                            action not in shielded and guarding.follow_up_name(guarding.method_name(action)),
                            (asked, slots))
            for action in actions}


@dataclass(frozen=True)
class _Judged:
    """One action's candidates as the evidence sees them."""

    results: Sequence[CandidateResult]
    origins: Mapping[str, str]
    index: OccurrenceIndex
    judged: dict[str, Evidence]
    verdicts: dict[str, Verdict]

    def candidates(self, *fates: Verdict) -> list[Candidate]:
        """The candidates of those fates; never the arithmetic of a tool spec nor an earlier write on the key
        (`tool_relations.labels_only`), which only separate labelled calls: a count that fits the demonstrations,
        or the order the logs made their writes in, is a correlate."""
        return [Candidate(r.expression, self.origins.get(r.expression, "model"), r.satisfied)
                for r in self.results if self.verdicts.get(r.expression) in fates and not labels_only(r.expression)]


def _judged(action: str, info: ActionInfo, inference: Inference) -> _Judged:
    results = inference.evaluated.results.get(action, ())
    index = OccurrenceIndex.of(inference.evaluated.points.get(action, ()), info.occurrences)
    judged = {r.expression: gather(r.satisfied, index) for r in results if r.status != "rejected"}
    tolerance = inference.options.tolerance
    verdicts = {r.expression: _verdict(r, judged[r.expression], tolerance) for r in results if r.status != "rejected"}
    return _Judged(results, inference.proposals.source.get(action, {}), index, judged, verdicts)


@dataclass(frozen=True)
class _Chosen:
    choice: cautious.Choice
    valid: list[Candidate]
    clusters: list[Cluster]
    cut: list[Cluster]
    """What the criterion chose and the tolerance's budget left out."""
    slipped: list[str] = field(default_factory=list)
    """Kept rules with exceptions by `options.answer_slips` (`cautious.slipped`): tolerated, not refuted."""


def _select(action: str, inference: Inference, turns: Mapping[tuple[int, int], int], tool_call: bool,
            conversational: bool, follow_up: bool = False,
            asked: tuple[Mapping[tuple[int, int], frozenset[str]], frozenset[str]] | None = None) -> Ranked:
    options, info = inference.options, inference.trace.actions[action]
    points = inference.evaluated.points.get(action, ())
    seen = _judged(action, info, inference)
    evidence = ActionEvidence(points, info.occurrences, turns, info.params, seen.index.mask,
                              not info.occurrences or thin(seen.index.occurrences, options.tolerance),
                              options.tolerance, inference.writes if options.ranking == "cautious" else {},
                              *(asked or ({}, frozenset())))
    votes = inference.proposals.votes.get(action, {})
    chosen = _choose(seen, evidence, options, votes, info, tool_call, conversational, follow_up)
    choice = chosen.choice
    if tool_call and options.ranking == "cautious" and not conversational:
        choice = categorical.refined(choice)
    if not evidence.thin and too_few(info.occurrences):  # strict validation on one or two calls: not established
        choice = replace(choice, decided={e: "assumed" if d == "established" else d for e, d in choice.decided.items()})
    transferred: dict[str, str] = {}
    prior = inference.prior
    if prior is not None and prior.rules.get(action):
        choice = _with_priors(choice, prior, action, seen.results, seen.verdicts, evidence)
        choice, slipped = _read_priors(choice, seen, evidence, options, conversational, too_few(info.occurrences))
        choice = priors.signed(choice, prior, action, seen.results, seen.verdicts)
        chosen = replace(chosen, slipped=[*chosen.slipped, *slipped])
        transferred = {e: prior.source_of(action, e) or "" for e, d in choice.decided.items() if d == "transferred"}
    reported, judged, verdicts = _with_composites(choice, seen.results, seen.judged, seen.verdicts, seen.index)
    verdicts |= {e: "tolerated" for e in chosen.slipped if e in choice.decided}
    reasons = {**_screened(verdicts, judged, options.tolerance, {r.expression: r.reason for r in seen.results}),
               **explain(options.ranking, chosen.valid, chosen.clusters, choice.chosen, evidence, votes, chosen.cut)}
    reasons |= _decided_reasons(choice, reasons)
    reasons |= {c.representative.expression: why for c, why in choice.offered}
    return Ranked(reported, chosen.valid, chosen.clusters, choice.chosen, reasons, judged, verdicts, choice.decided,
                  transferred, choice.search, unguarded_note(choice.unguarded), behind_note(choice.behind))


def _read_priors(choice: cautious.Choice, seen: _Judged, evidence: ActionEvidence, options: InferOptions,
                 conversational: bool, few: bool) -> tuple[cautious.Choice, list[str]]:
    """The rules with the priors, read as the action's own are (`cautious.slipped`): a transferred `not x` beside
    an own `x is not None` (or the reverse) leaves the presence test out, and a transferred presence test (another
    service's guess that a notice needs an answer) is read for the value its own calls show. A rule read from
    the calls is theirs again: established, or assumed on one or two of them. Also the kept rules with
    exceptions."""
    notes: dict[str, str] = {}
    replaced: dict[str, str] = {}
    if conversational or strict(options.tolerance) or options.answer_slips <= 0 or options.ranking != "cautious":
        read = cautious.unread(choice.chosen)
    else:
        atoms = informative(cluster(seen.candidates("held", "tolerated", "thin", "chance", "refuted")),
                            len(evidence.points))
        read, notes, replaced = cautious.slipped(choice.chosen, atoms, evidence, options.answer_slips)
    own: Decided = "assumed" if few else "established"
    decided = {**choice.decided, **{new: own if choice.decided.get(old) in (None, "transferred")
                                    else choice.decided[old] for new, old in replaced.items()}}
    kept = {c.representative.expression for c in read}
    return replace(choice, chosen=read, decided={e: d for e, d in decided.items() if e in kept},
                   notes={**{e: n for e, n in choice.notes.items() if e in kept}, **notes}), [
        e for e in notes if e in kept]


def unguarded_note(rules: Sequence[str]) -> str:
    if not rules:
        return ""
    return (f"conversational act (not in options.guarded): not kept, as its calls do not establish them: "
            f"{'; '.join(rules)}")


def behind_note(rules: Sequence[str]) -> str:
    if not rules:
        return ""
    return ("not kept: the other party's yes came before every call and covers what it said before (review "
            f"them): {'; '.join(rules)}")


def _choose(seen: _Judged, evidence: ActionEvidence, options: InferOptions, votes: Mapping[str, int],
            info: ActionInfo, tool_call: bool, conversational: bool, follow_up: bool) -> _Chosen:
    """The criterion's rules, within the tolerance's budget; an action too thinly demonstrated ranks like an
    unseen one (the hook for the spec's zero-shot judgment)."""
    n_points = len(evidence.points)
    if evidence.thin:
        valid = seen.candidates("held", "tolerated", "thin")
        choice = _zero_shot(valid, votes, info.params)
        if options.ranking == "cautious" and info.occurrences:
            choice = _with_thin(choice, seen.candidates("held", "tolerated", "thin", "chance", "refuted"),
                                evidence, n_points, tool_call, conversational)
        if conversational:  # a guess never refuses a conversational act: named, not kept
            kept = cautious.served(cluster(seen.candidates("held", "tolerated", "thin", "chance")), evidence) \
                if follow_up and options.ranking == "cautious" else []
            named = [*(c.representative.expression for c in choice.chosen), *choice.unguarded]
            choice = cautious.Choice(kept, {c.representative.expression: "assumed" for c in kept}, {}, choice.search,
                                     [e for e in named if all(e != c.representative.expression for c in kept)])
        return _Chosen(choice, valid, [], [])
    valid = seen.candidates("held", "tolerated")
    clusters = informative(cluster(valid), n_points)
    if options.ranking == "cautious":
        common = informative(cluster(seen.candidates("held", "tolerated", "chance")), n_points)
        atoms = informative(cluster(seen.candidates("held", "tolerated", "chance", "refuted")), n_points)
        found = cautious.choose(clusters, common, atoms, evidence, tool_call, conversational, follow_up)
        kept = within_budget(found.chosen, evidence)
        cut = [c for c in found.chosen if c not in kept]
        decided, notes = dict(found.decided), dict(found.notes)
        slips: dict[str, str] = {}
        if not conversational and not strict(options.tolerance) and options.answer_slips > 0:
            read, slips, replaced = cautious.slipped(kept, atoms, evidence, options.answer_slips)
            decided |= {new: decided.get(old, "established") for new, old in replaced.items()}
            decided = {e: d for e, d in decided.items() if any(c.representative.expression == e for c in read)}
            kept, notes = read, {**{e: n for e, n in notes.items() if e in decided}, **slips}
        return _Chosen(replace(found, chosen=kept, decided=decided, notes=notes), valid, clusters, cut, list(slips))
    picked = by_criterion(options.ranking, clusters, evidence)
    kept = within_budget(picked, evidence)
    return _Chosen(cautious.Choice(kept, {c.representative.expression: "established" for c in kept}), valid,
                   clusters, [c for c in picked if c not in kept])


def previous_turns(trace: TraceResult) -> dict[tuple[int, int], int]:
    """For each occurrence, where the observations since the agent's previous turn begin.

    A turn is a run of consecutive actions (an SGD system turn often holds several acts); going back from an
    occurrence over its own turn and then over the observations before it finds the previous turn's end.
    """
    acting: dict[int, set[int]] = {}
    for info in trace.actions.values():
        if info.stub:
            for occ in info.occurrences:
                acting.setdefault(occ.demo, set()).add(occ.position)
    starts: dict[tuple[int, int], int] = {}
    for demo, positions in acting.items():
        for position in positions:
            k = position - 1
            while k in positions:
                k -= 1
            while k >= 0 and k not in positions:
                k -= 1
            starts[(demo, position)] = k + 1
    return starts


def confirmations(trace: TraceResult, turns: Mapping[tuple[int, int], int]
                  ) -> tuple[dict[tuple[int, int], frozenset[str]], frozenset[str]]:
    """For each agent action's occurrence whose observations answered a confirmation or an offer (an act named
    CONFIRM or OFFER in the agent's turn right before them: `CONFIRM('time')`, then the user's yes), the slots it
    covers: those the dialog's confirmations named before (a re-confirmation of a changed time keeps the city
    confirmed earlier) and those the answered offer named; `cautious.ANY_SLOT` for one that names none
    (`ASK_CONFIRM_BOOKING()`). Absent where the turn before asked neither: that yes confirmed nothing. Also every
    slot the agent's acts name (requests, offers, confirmations): a fact about any other key (an intent) or no key
    (`selected`) is no slot a confirmation could name, and the yes covers it as before."""
    confirm: dict[int, dict[int, set[str]]] = {}
    offer: dict[int, dict[int, set[str]]] = {}
    asks: dict[int, dict[int, set[str]]] = {}
    for name, info in trace.actions.items():
        word = guarding.method_name(name).upper()
        table = confirm if "CONFIRM" in word else offer if "OFFER" in word else asks if "REQUEST" in word else None
        if table is None or not info.stub:
            continue
        for occ in info.occurrences:
            values = {v for v in occ.args if isinstance(v, str)} or {cautious.ANY_SLOT}
            table.setdefault(occ.demo, {}).setdefault(occ.position, set()).update(values)
    out: dict[tuple[int, int], frozenset[str]] = {}
    for (demo, position), start in turns.items():
        before = turns.get((demo, start - 1))
        turn = range(start - 1, -1, -1) if before is not None else range(0)
        asked = [k for k in turn if turns.get((demo, k)) == before]
        if not any(k in confirm.get(demo, {}) or k in offer.get(demo, {}) for k in asked):
            continue
        slots = {v for k, values in confirm.get(demo, {}).items() if k < start for v in values}
        slots |= {v for k in asked for v in offer.get(demo, {}).get(k, set())}
        out[(demo, position)] = frozenset(slots)
    named = {v for table in (confirm, offer, asks) for by_position in table.values() for values in by_position.values()
             for v in values}
    return out, frozenset(named - {cautious.ANY_SLOT})


def _zero_shot(valid: Sequence[Candidate], votes: Mapping[str, int], params: Sequence[str]) -> cautious.Choice:
    chosen = zero_shot(valid, votes, params)
    return cautious.Choice(chosen, {c.representative.expression: "zero-shot" for c in chosen})


def _with_thin(choice: cautious.Choice, judged: Sequence[Candidate], evidence: ActionEvidence, n_points: int,
               tool_call: bool, conversational: bool) -> cautious.Choice:
    """A thinly demonstrated action keeps, besides the model's zero-shot rule, what the cautious criterion would
    keep from its few calls: assumed, not established (one or two calls cannot tell a requirement from a
    coincidence). A conversational act names them instead (`cautious.choose`)."""
    kept = {c.satisfied for c in choice.chosen}
    extra = [c for c in cautious.thin_rules(judged, evidence, n_points, tool_call) if c.satisfied not in kept]
    if conversational:
        return replace(choice, unguarded=[c.representative.expression for c in extra])
    chosen = cautious.unread([*choice.chosen, *extra])
    decided: dict[str, Decided] = {**choice.decided, **{c.representative.expression: "assumed" for c in extra}}
    return replace(choice, chosen=chosen,
                   decided={e: d for e, d in decided.items() if any(c.representative.expression == e for c in chosen)})


def _with_priors(choice: cautious.Choice, prior: priors.Priors, action: str, results: Sequence[CandidateResult],
                 verdicts: Mapping[str, Verdict], evidence: ActionEvidence) -> cautious.Choice:
    """The hook of `engine.priors`: the surviving priors most sources name, preferred where the evidence does not
    decide."""
    found = list(prior.rules[action].values())
    best = priors.preferred(found, {r.expression: r for r in results}, verdicts, evidence, bool(evidence.occurrences),
                            evidence.thin)
    common = frozenset(e for e, v in verdicts.items() if v == "chance")
    return priors.prefer(choice, best, priors.support(found), evidence.thin, evidence.params, common)


def _with_composites(choice: cautious.Choice, results: Sequence[CandidateResult], judged: dict[str, Evidence],
                     verdicts: dict[str, Verdict], index: OccurrenceIndex
                     ) -> tuple[Sequence[CandidateResult], dict[str, Evidence], dict[str, Verdict]]:
    """Rules the ranking composed (disjunctions), chosen or only offered to a reviewer, join the reports like any
    candidate; their satisfaction set is the union of their terms' (verification then runs the chosen ones in the
    sandbox like every kept rule)."""
    known = {r.expression for r in results}
    composed = [*choice.chosen, *(c for c, _ in choice.offered)]
    extra = list({c.representative.expression: c.representative for c in composed
                  if c.representative.expression not in known}.values())
    if not extra:
        return results, judged, verdicts
    judged, verdicts = dict(judged), dict(verdicts)
    for candidate in extra:
        judged[candidate.expression] = gather(candidate.satisfied, index)
        verdicts[candidate.expression] = "held" if not index.mask & ~candidate.satisfied else "tolerated"
    rows = [CandidateResult(c.expression, "valid", None, c.satisfied) for c in extra]
    return (*results, *rows), judged, verdicts


def _decided_reasons(choice: cautious.Choice, ranked: Mapping[str, str]) -> dict[str, str]:
    """The reason of a rule that only the cautious criterion keeps: composed, or assumed (a rule the ranking kept
    for what enabled the calls, assumed only for how few they were, keeps the ranking's reason)."""
    reasons = {e: f"kept: {note}" for e, note in choice.notes.items()}
    for expression, decided in choice.decided.items():
        if decided == "assumed" and expression not in reasons and not ranked.get(expression, "").startswith("kept"):
            reasons[expression] = (
                "assumed: held at every demonstrated call and nothing shows the call can happen without it, though "
                "the evidence cannot tell it from a correlate (true long before, common everywhere, or implied by "
                "another rule only on the demonstrated points); kept so the guard does not pick the permissive "
                "side silently: review it")
    return reasons


def _receiver(source: str) -> str | None:
    """The object a step's statement calls a method on (`system` in `system.FindBus()`), if it is such a call."""
    try:
        node = ast.parse(source.strip()).body[0]
    except (SyntaxError, IndexError, RecursionError, ValueError):
        return None
    if isinstance(node, ast.Expr) and isinstance(node.value, ast.Call) and isinstance(node.value.func, ast.Attribute) \
            and isinstance(node.value.func.value, ast.Name):
        return node.value.func.value.id
    return None


def _tool_calls(trace: TraceResult) -> set[str]:
    """The actions that are tool calls: at least half of their calls are answered by an observation on the same
    object (a service's result, `system.set_query_status(True)` after `system.FindBus()`), not by another
    party's turn. Read once per inference from the trace's statements."""
    acting = {(o.demo, o.position) for info in trace.actions.values() if info.stub for o in info.occurrences}
    tools: set[str] = set()
    for action, info in trace.actions.items():
        if not info.stub:
            continue
        answered = 0
        for occ in info.occurrences:
            steps = trace.positions[occ.demo]
            following = occ.position + 1
            if following < len(steps) and (occ.demo, following) not in acting \
                    and _receiver(steps[following].source) == _receiver(steps[occ.position].source):
                answered += 1
        if info.occurrences and answered * 2 >= len(info.occurrences):
            tools.add(action)
    return tools


def _verdict(result: CandidateResult, evidence: Evidence, tolerance: float) -> Verdict:
    """Tolerance 0 is the paper's validation exactly: the sandbox's own verdict at every occurrence."""
    if strict(tolerance):
        return "held" if result.status == "valid" else "refuted"
    return verdict(evidence, tolerance)


def _screened(verdicts: Mapping[str, Verdict], judged: Mapping[str, Evidence], tolerance: float,
              first_violation: Mapping[str, str | None]) -> dict[str, str]:
    """Why evidence-weighted validation turned a candidate away (strict validation: the sandbox says why),
    naming the first violated occurrence (demonstration, line) as the sandbox found it."""
    if strict(tolerance):
        return {}
    reasons: dict[str, str] = {}
    for expression, fate in verdicts.items():
        e = judged[expression]
        where = first_violation.get(expression)
        first = f"; first violated at {where}" if where else ""
        if fate == "refuted":
            reasons[expression] = (f"refuted: {describe(e)}; more exceptions than slips at the tolerance "
                                   f"({tolerance:.0%}) explain{first}")
        elif fate == "chance":
            reasons[expression] = (f"not separated from chance: {describe(e)}; holding this often at the "
                                   f"occurrences is likely (p = {e.chance():.2f}) for a condition that common{first}")
    return reasons
