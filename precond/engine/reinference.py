"""A re-inference merged with the base version of a precondition set: every rule marked required is kept,
no rule marked rejected comes back, and every change is in the diff with its reason (the candidate report's,
or where a removed rule would have blocked a demonstrated call). Pure: the worker runs it after the inference
and stores the result (`worker.reinfer`).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

from precond.programs.checks import normal
from precond_client.schemas.api import CandidateReport, PreconditionSet, RuleChange, SetDiff


def _has(table: Mapping[str, Sequence[str]], action: str, rule: str) -> bool:
    return normal(rule) in {normal(r) for r in table.get(action, ())}


@dataclass(frozen=True)
class Merged:
    preconditions: dict[str, list[str]]
    diff: SetDiff
    unexplained: dict[str, list[str]]
    """Rules of the base version that are gone and that no candidate of the inference explains: the caller
    judges them against the demonstrations to say why (violated where, or still holding but not re-proposed)."""


def merge(
    base: PreconditionSet, inferred: Mapping[str, Sequence[str]],
    candidates: Mapping[str, Sequence[CandidateReport]], new_demonstrations: int = 0,
    actions: Collection[str] | None = None,
) -> Merged:
    """The rules of the version a re-inference makes from `base`, and what changed.

    Kept: every required rule of the base (first, in its order), the rules of actions not re-inferred (when
    `actions` names the re-inferred ones), then every inferred rule that is not marked rejected. Rules are
    compared by their canonical text. A base rule that is gone is reported with the reason its candidate was
    dropped, when the inference judged it; otherwise it is in `unexplained`.
    """
    rules: dict[str, list[str]] = {}
    diff = SetDiff(base_version=base.version, new_demonstrations=new_demonstrations)

    def keep(action: str, rule: str) -> None:
        if not _has(rules, action, rule):
            rules.setdefault(action, []).append(rule)

    for action, required in base.required.items():
        for rule in required:
            keep(action, rule)
            diff.required_kept.append(RuleChange(action=action, rule=rule, reason="marked required"))
    for action, old_rules in base.preconditions.items():
        if actions is not None and action not in actions:  # not re-inferred: stays as it is
            for rule in old_rules:
                if not _has(base.required, action, rule):
                    keep(action, rule)
                    diff.kept.append(RuleChange(action=action, rule=rule, reason="not re-inferred (not in `actions`)"))
    reports = {a: {normal(c.assertion): c for c in cs} for a, cs in candidates.items()}
    for action, inferred_rules in inferred.items():
        for rule in inferred_rules:
            report = reports.get(action, {}).get(normal(rule))
            reason = report.reason if report is not None else None
            if _has(base.rejected, action, rule):
                diff.rejected_suppressed.append(RuleChange(action=action, rule=rule, reason="marked rejected"))
            elif _has(base.required, action, rule):
                continue
            elif _has(base.preconditions, action, rule):
                keep(action, rule)
                diff.kept.append(RuleChange(action=action, rule=rule, reason=reason))
            else:
                keep(action, rule)
                diff.added.append(RuleChange(action=action, rule=rule, reason=reason))
    unexplained: dict[str, list[str]] = {}
    for action, old_rules in base.preconditions.items():
        for rule in old_rules:
            if _has(rules, action, rule):
                continue
            report = reports.get(action, {}).get(normal(rule))
            if report is not None and not report.kept:
                diff.removed.append(RuleChange(action=action, rule=rule, reason=report.reason or "dropped"))
            else:
                unexplained.setdefault(action, []).append(rule)
    return Merged(preconditions=rules, diff=diff, unexplained=unexplained)


def explain_removed(merged: Merged, blocked: Mapping[tuple[str, str], str]) -> SetDiff:
    """`merged.diff` with a reason for each unexplained removal: the first demonstrated call it would have
    blocked (`blocked[(action, rule)]`, in words), or that it still holds but was not proposed again."""
    removed = list(merged.diff.removed)
    for action, rules in merged.unexplained.items():
        for rule in rules:
            why = blocked.get((action, rule))
            reason = (f"violated at {why}" if why else "still holds at every demonstration, but the re-inference "
                      "did not propose or keep it; add it back, or mark it required to keep it")
            removed.append(RuleChange(action=action, rule=rule, reason=reason))
    return merged.diff.model_copy(update={"removed": removed})
