"""An inference's top-level warnings, assembled from every stage that has something to say about an action.

Each rule's own case (empty, assumed, zero-shot: `notices.rule_warnings`) comes first; then what a stage dropped
or could not do for the action: candidates that raise on the spec's state or ran out of time in the sandbox,
labelled calls no rule separates, a search cut at its bound, an act whose rules a guard does not keep; and the
demonstrations left out as too large to judge. One place, so that the engine's inference reads as its stages and
nothing a stage says is silently lost (docs/api.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from precond.engine.judging import counterexamples
from precond.engine.judging import guarded as guarding
from precond.engine.judging.notices import rule_warnings
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.sandbox.types import TIMED_OUT, EvaluateResult, TraceResult
from precond_client.schemas import Decided, InferOptions


@dataclass(frozen=True)
class Findings:
    """What the stages of one inference found, as its warnings need it."""

    actions: Sequence[str]
    trace: TraceResult
    preconditions: Mapping[str, list[str]]
    ranked: Mapping[str, Ranked]
    options: InferOptions
    generated: bool
    """The code model proposed rules (a rule without evidence is then its zero-shot guess)."""
    prior_dropped: Mapping[str, Sequence[str]]
    unrunnable: Mapping[str, Mapping[str, str]]
    evaluated: EvaluateResult
    separated: Mapping[str, counterexamples.Separation]
    guarded: Sequence[str]
    stopped: Mapping[str, str]
    left_out: Mapping[int, str]


def decided_of(findings: Findings) -> dict[str, dict[str, Decided]]:
    """How each kept rule was decided: the ranking's word, `unseen` for the placeholder of an unseen action."""
    return {a: {rule: findings.ranked[a].decided.get(rule, "unseen" if rule == UNSEEN_RULE else "established")
                for rule in findings.preconditions[a]} for a in findings.actions}


def inference_warnings(findings: Findings) -> dict[str, str]:
    """Per action (and per left-out demonstration), every warning the inference's stages left, joined by '; '."""
    f = findings
    occurrences = {a: f.trace.actions[a].occurrences for a in f.actions}
    warnings = rule_warnings(f.actions, occurrences, f.preconditions, decided_of(f), f.generated, f.options,
                             f.prior_dropped)
    for action, dropped in f.unrunnable.items():
        listed = "; ".join(f"`{e}` ({why})" for e, why in list(dropped.items())[:3])
        _add(warnings, action, f"{len(dropped)} candidate(s) dropped: they raise on the spec's state: {listed}")
    for action, slow in timed_out(f.evaluated).items():
        _add(warnings, action, f"{slow} candidate(s) dropped: they ran out of time in the sandbox (SANDBOX_TIMEOUT_S), "
                               "judged alone too; the others were judged")
    for action, separation in f.separated.items():
        _add(warnings, action, *separation.conflicts)
        if separation.unrefused:
            _add(warnings, action, unrefused(separation.unrefused, f.preconditions[action] == [UNSEEN_RULE]))
    _add_cuts(warnings, f)
    warnings.update({f"demonstrations[{i}]": why for i, why in f.left_out.items()})
    return warnings


def _add(warnings: dict[str, str], action: str, *said: str) -> None:
    """Join what is said of an action to its warning, if anything is."""
    if any(said):
        warnings[action] = "; ".join(w for w in (warnings.get(action), *said) if w)


def _add_cuts(warnings: dict[str, str], f: Findings) -> None:
    """A search cut at its bound, or the rules an act does not keep, say so."""
    default = "" if f.options.guarded is not None else guarding.note(list(f.guarded))
    for action in f.actions:
        unseen = not f.trace.actions[action].occurrences
        unguarded_rule = action not in f.guarded and not f.preconditions[action] and unseen
        said = f.ranked[action].unguarded or (guarding.UNREFUSED if unguarded_rule else "")
        unguarded = "; ".join(w for w in (said, default) if said and w)
        _add(warnings, action, *(w for w in (f.stopped.get(action), f.ranked[action].search,
                                             f.ranked[action].behind, f.ranked[action].assumed, unguarded) if w))


def timed_out(evaluated: EvaluateResult) -> dict[str, int]:
    """Per action, the candidates the sandbox dropped for running out of time: each is left out and counted, the
    request goes on."""
    counts = {a: sum((r.reason or "").startswith(TIMED_OUT) for r in results) for a, results in
              evaluated.results.items()}
    return {a: n for a, n in counts.items() if n}


def unrefused(names: Sequence[str], placeholder: bool) -> str:
    """The warning of an action whose calls labelled 'refuse' no learned rule refuses: which, and what refuses
    them instead (the placeholder of a never-demonstrated action) or that nothing does."""
    listed = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    then = ("the action stays refused (options.unseen: 'refuse')" if placeholder
            else "the rules allow them: review them, or write the rule")
    return (f"unseparated: {len(names)} call(s) labelled 'refuse' ({listed}) that no learned condition "
            f"refuses (none separates them from the calls to allow or, with none to allow, states a limit they "
            f"break); {then}")
