"""A re-inference merged with the base version of a precondition set: every rule marked required is kept,
no rule marked rejected comes back, and every change is in the diff with its reason (the candidate report's,
or where a removed rule would have blocked a demonstrated call), and the store of the version it makes: appended
only if its base is still the latest (`store`, with the refusals a client can act on). The merge is pure: the worker
runs it after the inference (`worker.reinfer`), then stores its version on the event loop.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from precond.jobs.queue.payloads import ReinferJob
from precond.programs.checks import normal
from precond.store import sets, tenant_store
from precond_client.schemas import CandidateReport, PreconditionSet, RuleChange, SetDiff
from precond_client.schemas.errors import Conflict, SetsLimited


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


async def store(redis: Any, tenant: str, job: ReinferJob, version: PreconditionSet) -> PreconditionSet:
    """Append the version if its base is still the latest; the errors a client can act on otherwise."""
    record = version.model_dump_json()
    if len(record.encode()) > job.max_bytes:
        raise SetsLimited(f"the re-inferred version takes {len(record.encode()):,} bytes, over the bound of "
                          f"{job.max_bytes:,} (PRECOND_MAX_SET_BYTES)", field="demonstrations")
    bounds = tenant_store.Bounds(records=0, versions=job.max_versions, tenant_bytes=job.max_tenant_bytes or 0)
    answer = await sets.put(redis, tenant, version, record, bounds)
    if answer == tenant_store.TOO_MANY_BYTES:
        raise SetsLimited(sets.tenant_bytes_message(job.max_tenant_bytes or 0))
    if answer == tenant_store.CONFLICT:
        mine = await _stored_by_an_earlier_run(redis, tenant, version)
        if mine is not None:
            return mine
    if answer in (tenant_store.CONFLICT, tenant_store.MISSING):
        raise Conflict(f"precondition set {version.id} got a new version while it was re-inferred from version "
                       f"{job.base.version}: read the latest and re-infer again")
    if answer == tenant_store.TOO_MANY_VERSIONS:
        raise SetsLimited(f"precondition set {version.id} has {job.max_versions} versions, the bound "
                          "(PRECOND_MAX_SET_VERSIONS): create a new set from its latest version")
    return version.model_copy(update={"latest": answer})


async def _stored_by_an_earlier_run(redis: Any, tenant: str, version: PreconditionSet) -> PreconditionSet | None:
    """The version this job makes, when an earlier run of it stored it already (its worker died before arq
    recorded the end, and the job was handed back): the same rules, demonstrations and diff at the same number."""
    raw = await tenant_store.read(redis, tenant_store.SETS, tenant, version.id, version.version)
    latest = await tenant_store.latest(redis, tenant_store.SETS, tenant, version.id)
    if raw is None or latest is None:
        return None
    stored = PreconditionSet.model_validate_json(raw)
    same = ("preconditions", "demonstrations", "required", "rejected", "diff")
    if any(getattr(stored, name) != getattr(version, name) for name in same):
        return None
    return stored.model_copy(update={"latest": latest})
