"""The pieces of an inference that are not the Engine's own: the request as read and traced (`Run`), which
actions the model is asked about, the candidates' sources merged, the rules chosen and the points they may refuse,
the questions left to the code model as judge, and the phases' timer. The Engine (`engine.py`) runs the stages.
"""

from __future__ import annotations

import ast
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from precond.engine.candidates.tool_facts import tool_class
from precond.engine.judging import counterexamples, judge, priors
from precond.engine.judging import guarded as guarding
from precond.engine.judging.decisive import decisive_points
from precond.engine.judging.evidence import thin, too_few
from precond.engine.judging.ranking import (
    cluster,
    informative,
)
from precond.engine.judging.report import UNSEEN_RULE, Proposals, Ranked
from precond.engine.left_out import Traced
from precond.engine.spec import (
    Spec,
    as_error,
)
from precond.programs import checks
from precond.sandbox.types import (
    EvaluateResult,
    Point,
    ProgramError,
    TraceResult,
)
from precond_client.schemas import (
    InferOptions,
    InferRequest,
    RuleEvidence,
)

if TYPE_CHECKING:
    pass



class Timer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - start, 4)


@dataclass(frozen=True)
class Run:
    """An inference's request as read and traced: what every later stage reads."""

    request: InferRequest
    spec: Spec
    actions: list[str]
    demos: list[str]
    demo_trees: list[ast.Module]
    labelled: counterexamples.Labelled | None
    prior: priors.Priors
    guarded: list[str]
    traced: Traced
    judged_at: dict[str, list[Point]]

    @property
    def trace(self) -> TraceResult:
        return self.traced.trace


def chosen_rules(run: Run, ranked: Mapping[str, Ranked], separated: Mapping[str, counterexamples.Separation]
            ) -> dict[str, list[str]]:
    """Each action's chosen rules; under `unseen: refuse`, the placeholder for a guarded action with no rule that
    was never demonstrated (or whose labelled calls show nothing), unless a call of it is labelled 'allow' and
    none 'refuse'."""
    chosen = {a: [c.representative.expression for c in ranked[a].chosen] for a in run.actions}
    if run.request.options.unseen != "refuse":
        return chosen
    labelled = run.labelled
    shown = {c.action for c in labelled.cases if c.verdict == "allow"} - {
        c.action for c in labelled.cases if c.verdict == "refuse"} if labelled else set()
    unshown = {a for a, s in separated.items() if s.unshown}
    chosen.update({a: [UNSEEN_RULE] for a in run.guarded if (not run.trace.actions[a].occurrences or a in unshown)
                   and not chosen[a] and a not in shown})
    return chosen


def exempt_points(chosen: Mapping[str, Sequence[str]], ranked: Mapping[str, Ranked],
            separated: Mapping[str, counterexamples.Separation]) -> dict[int, set[int]]:
    """The demonstrated points the chosen rules may refuse: their tolerated exceptions and the labelled calls."""
    exempt = exceptions_of(chosen, ranked)
    for separation in separated.values():
        for point in separation.exempt:
            exempt.setdefault(point.demo, set()).add(point.position)
    return exempt


def with_separations(evidence: dict[str, dict[str, RuleEvidence]],
                      separated: Mapping[str, counterexamples.Separation]) -> None:
    """Each kept rule's evidence with the labelled calls it refuses."""
    for action, separation in separated.items():
        for rule, kept in evidence[action].items():
            evidence[action][rule] = kept.model_copy(update={
                "refuses": separation.refuses.get(rule, []),
                "refuses_allowed": separation.refuses_allowed.get(rule, [])})


def prompted_actions(actions: Sequence[str], trace: TraceResult, options: InferOptions) -> list[str]:
    """The actions the model is asked about: all, or (`model_for: thin`, with the enumerator on to cover the
    others) those too thinly demonstrated to learn from, never demonstrated included."""
    if options.model_for == "all" or "enumerate" not in options.generators:
        return list(actions)
    return [a for a in actions if too_few(trace.actions[a].occurrences)]


def proposals_of(actions: Sequence[str], enumerated: Proposals, prior: priors.Priors,
              sampled: Proposals | None = None) -> Proposals:
    """The model's samples (if any), then the enumerator's atoms, then the priors: the order that decides which
    generator a candidate is reported from and which text stands for its cluster."""
    proposals = sampled if sampled is not None else Proposals()
    for action in actions:
        proposals.add(action, list(enumerated.source.get(action, {})), "enumerate", enumerated.sampled.get(action, 0))
        proposals.add(action, prior.expressions(action), "prior", 0)  # without priors, nothing changes
    return proposals


def known_rules(spec: Spec, prompted: Sequence[str], ranked: Mapping[str, Ranked]) -> dict[str, list[str]]:
    """The rules the evidence chose for the actions of the prompted ones' classes, to show the model."""
    classes = {spec.methods[a].cls for a in prompted}
    return {a: [c.representative.expression for c in r.chosen] for a, r in ranked.items()
            if r.chosen and spec.methods[a].cls in classes}


def merged(first: EvaluateResult | None, rest: EvaluateResult) -> EvaluateResult:
    """The settled actions' judgments (made before the model was asked) beside the rest's: none judged twice."""
    if first is None:
        return rest
    return EvaluateResult({**rest.points, **first.points}, {**rest.results, **first.results})


def without_left_out(request: InferRequest, traced: Traced) -> InferRequest:
    """The request with the left-out demonstrations empty and without the labelled calls of their runs."""
    runs = [r for r in request.counterexamples if r.demonstration not in traced.left_out]
    return request.model_copy(update={"demonstrations": traced.demonstrations, "counterexamples": runs})


def separable(ranked: Ranked, policy: set[str] | None) -> list[str]:
    """The judged conditions the labelled calls are separated by (`counterexamples.separate`): every one, or for a
    tool spec the ranking's kept rules and the conditions over results and arguments (`policy`), the only ones
    its separation reads; the rest need not be judged again at the labelled calls."""
    kept = {c.representative.expression for c in ranked.chosen}
    return list(dict.fromkeys(r.expression for r in ranked.results if r.status != "rejected" and (
        not policy or r.expression in policy or r.expression in kept)))


def judged_at(spec: Spec, actions: Sequence[str], trace: TraceResult) -> dict[str, list[Point]]:
    """A tool-calling agent's actions judged where a condition decides something (`engine.decisive`), those whose
    default grid is larger; every other action keeps the default grid."""
    cls = tool_class(spec)
    methods = [q for q, m in spec.methods.items() if m.cls == cls]
    found = {a: decisive_points(trace, trace.actions[a], methods) for a in actions
             if cls is not None and spec.methods[a].cls == cls}
    return {a: points for a, points in found.items() if points is not None}


def refuse_no_evidence(actions: Sequence[str], trace: TraceResult) -> None:
    """No demonstration calls any of the actions: nothing to learn from (422); some: `notices` warns of each."""
    if not any(trace.actions[a].occurrences for a in actions):
        raise as_error(checks.no_occurrence_problem(list(actions), trace_count(trace)))


def trace_count(trace: TraceResult) -> int:
    return len(trace.positions)


def same_place(a: ProgramError | None, b: ProgramError) -> bool:
    return a is not None and (a.where, a.index, a.line) == (b.where, b.index, b.line)


def action_at(spec: Spec, demo: str, line: int, preconditions: dict[str, list[str]]) -> str | None:
    """The action with kept assertions called on a demonstration line (the one whose assertion failed)."""
    lines = demo.splitlines()
    text = lines[line - 1] if 0 < line <= len(lines) else ""
    for action, assertions in preconditions.items():
        if assertions and f".{spec.methods[action].name}(" in text:
            return action
    return None


def question(action: str, ranked: Ranked, trace: TraceResult, n_points: int,
              options: InferOptions) -> judge.Question | None:
    """What the evidence left open for `action`, if anything: a rule for an action never or too thinly
    demonstrated (zero-shot), or a condition that held but looked like a phase."""
    occurrences = trace.actions[action].occurrences
    if not occurrences or thin(occurrences, options.tolerance):
        # With parameters and no occurrence there are no points at all: every valid candidate is an option.
        clusters = informative(cluster(ranked.valid), n_points)
        vacuous = [c.representative.expression for c in clusters] or [c.expression for c in ranked.valid]
        return judge.question(action, "zero-shot", vacuous, []) if vacuous else None
    if options.ranking != "recency":
        return None
    everything = [c.representative.expression for c in ranked.clusters]
    open_ = [c.representative.expression for c in ranked.clusters
             if c not in ranked.chosen and not any(k.satisfied & ~c.satisfied == 0 for k in ranked.chosen)]
    return judge.question(action, "phase", open_, everything) if open_ else None


def exceptions_of(chosen: Mapping[str, Sequence[str]], ranked: Mapping[str, Ranked]) -> dict[int, set[int]]:
    """Demonstration -> positions of the calls that kept rules refuse by design (tolerated exceptions)."""
    steps: dict[int, set[int]] = {}
    for action, kept in chosen.items():
        for expression in kept:
            if ranked[action].verdicts.get(expression) == "tolerated":
                for occ in ranked[action].evidence[expression].exceptions:
                    steps.setdefault(occ.demo, set()).add(occ.position)
    return steps


def guarded_actions(spec: Spec, actions: Sequence[str], options: InferOptions) -> list[str]:
    try:
        return guarding.resolve(options.guarded, actions, spec.methods)
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc

