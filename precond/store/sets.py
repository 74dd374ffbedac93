"""Precondition sets as the gateway and the workers share them: where versions live in the queue Redis, the
atomic append of a version (the gateway for edits, a worker for re-inference), the review's summary of a
version and the union of stored and new demonstrations. The merge of a re-inference with its base version, and
its store, are `store.reinference`.

Sets are stored by `precond.store.tenant_store` (kind `SETS`: `precond:sets:<tenant>`, `precond:set:<tenant>:<id>`,
`precond:set-bytes:<tenant>`), with `created` (of version 1) and `summary` (of the latest) beside the versions.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any, Final

from pydantic import TypeAdapter, ValidationError

from precond.programs import checks
from precond.programs.checks import normal as normal  # re-exported: the sets code compares rules by it
from precond.store import tenant_store
from precond_client.rule_interpreter import Frame, constant_work
from precond_client.schemas import CandidateReport, Preconditions, PreconditionSet, RuleEvidence

RULE_CHARS = 200
"""A rule named in a refusal is cut to this many characters."""


def tenant_bytes_message(max_tenant_bytes: int) -> str:
    return (f"this tenant's precondition sets would take more than {max_tenant_bytes:,} bytes, the bound "
            "(PRECOND_MAX_SET_BYTES_PER_TENANT)")


async def put(redis: Any, tenant: str, version: PreconditionSet, record: str, bounds: tenant_store.Bounds) -> int:
    """Store `record` (version n's JSON) as version n if n-1 is still the latest (n = 1: a new set, within the
    tenant's bound of sets) and the tenant's sets stay within their bound of bytes: n, or a `tenant_store` code.
    The list of sets reads each set's creation time and its latest version's summary, kept beside the versions,
    so listing never reads whole versions."""
    beside = {"summary": summary(version)} | ({"created": version.created} if version.version == 1 else {})
    return await tenant_store.put(redis, tenant_store.SETS, tenant, version.id, version.version, record, bounds,
                                  beside=beside)


ESTABLISHED_AT: Final = 3
"""Occurrences below which a rule that held is only assumed: the engine's bound for thin evidence."""


def how_decided(evidence: RuleEvidence | None, report: CandidateReport | None) -> str:
    """How one rule was decided: the engine's own word (`RuleEvidence.decided`); for a report stored before the
    engine said it, read from the evidence and the candidate's reason."""
    if evidence is not None and evidence.decided is not None:
        return evidence.decided
    reason = (report.reason if report is not None else None) or ""
    if reason.startswith("kept by the code model's judgment"):
        return "zero-shot" if "never demonstrated" in reason else "assumed"
    if reason.startswith("zero-shot") or (evidence is not None and evidence.occurrences == 0):
        return "zero-shot"
    if evidence is None:
        return "no evidence"
    return "assumed" if evidence.verdict == "thin" or evidence.occurrences < ESTABLISHED_AT else "established"


def decided(preconditions: Mapping[str, Sequence[str]], evidence: Mapping[str, Mapping[str, RuleEvidence]],
            candidates: Mapping[str, Sequence[CandidateReport]]) -> dict[str, dict[str, str]]:
    """`how_decided` for every rule, its evidence and report matched by canonical text."""
    labels: dict[str, dict[str, str]] = {}
    for action, rules in preconditions.items():
        found = {normal(rule): ev for rule, ev in evidence.get(action, {}).items()}
        reports = {normal(c.assertion): c for c in candidates.get(action, ())}
        labels[action] = {rule: how_decided(found.get(normal(rule)), reports.get(normal(rule))) for rule in rules}
    return labels


def summary(version: PreconditionSet) -> str:
    """The latest version as the list of sets shows it (JSON; the set's creation time is stored apart)."""
    labels = [label for rules in version.decided.values() for label in rules.values()]
    known = {*version.preconditions, *version.candidates, *version.warnings, *version.rejected}
    return json.dumps({
        "id": version.id, "latest": version.version, "reference": version.reference, "updated": version.created,
        "actions": sorted(known), "rules": sum(len(r) for r in version.preconditions.values()),
        "assumed": labels.count("assumed"), "zero_shot": labels.count("zero-shot"),
        "no_evidence": sum(len(r) for r in version.preconditions.values()) - len(labels) + labels.count("no evidence"),
        "required": sum(len(r) for r in version.required.values()),
        "rejected": sum(len(r) for r in version.rejected.values()),
    })


_RULES: Final = TypeAdapter(Preconditions)


def over_bounds(rules: Mapping[str, Sequence[str]]) -> str | None:
    """Why a version's merged rules could not be sent with a request (the bounds of `Preconditions`: rules per
    action, actions, their lengths), or None. A version is stored only when every check naming it can use its
    rules: edits and re-inference merge rules that were each within the bounds into ones that may not be."""
    try:
        _RULES.validate_python(rules)
    except ValidationError as exc:
        error = exc.errors()[0]
        where, limits = error["loc"], error.get("ctx", {})
        if error["type"] == "too_long" and len(where) == 1:
            return (f"{where[0]} would have {limits['actual_length']} rules, over the {limits['max_length']} one "
                    "action may have")
        if error["type"] == "too_long" and not where:
            return f"{limits['actual_length']} actions would have rules, over the {limits['max_length']} a set may have"
        return f"preconditions.{'.'.join(map(str, where))}: {error['msg']}"
    return None


def check_set(spec: str, preconditions: Mapping[str, Sequence[str]], demonstrations: Sequence[str]) -> None:
    """A version's static check (`checks.check_set`), then what its rules cost the embedded guard regardless of
    the state (`check_rule_work`); raises ProgramProblem. One call, for the gateway's check pool."""
    checks.check_set(spec, preconditions, demonstrations)
    check_rule_work(preconditions)


def check_rule_work(preconditions: Mapping[str, Sequence[str]]) -> None:
    """A rule whose parts that read nothing of the state take the embedded guard past its budget (nested
    squarings of a constant) would be refused at every call, after burning the agent's CPU up to the bound: it is
    refused here instead, naming the rule and the bound. The parts are evaluated by the guard's own interpreter
    within one budget for the whole set (`rule_interpreter.constant_work`), so the check costs at most that."""
    frame = Frame(None, ())
    for action, rules in preconditions.items():
        for index, rule in enumerate(rules):
            problem = constant_work(rule, frame)
            if problem is not None:
                field = f"preconditions.{action}[{index}]"
                shown = rule if len(rule) <= RULE_CHARS else rule[:RULE_CHARS - 3] + "..."
                message = (f"{field}: the rule {shown!r} takes the embedded guard past its bounds at every call: "
                           f"{problem}")
                raise checks.ProgramProblem(checks.Problem(checks.WORK_BUDGET, field, message))


def union(stored: Sequence[str], new: Sequence[str]) -> list[str]:
    """The stored demonstrations, then the new ones not already stored (in their order)."""
    seen = set(stored)
    out = list(stored)
    for demo in new:
        if demo not in seen:
            seen.add(demo)
            out.append(demo)
    return out


def set_warnings(spec: str, rules: Mapping[str, Sequence[str]], rejected: Mapping[str, Sequence[str]],
                 known: Mapping[str, str]) -> dict[str, str]:
    """Per action of the spec whose rule in this version is empty or not backed by evidence, why: a reviewer's
    rejection that left it without a rule first (the inference's warning about it is then out of date), then
    the `known` warning (the inference's: no occurrence, thin evidence), then plainly no rule. An empty rule
    allows every call, so none is left unsaid."""
    _, methods = checks.spec_methods(spec)
    warnings: dict[str, str] = {}
    for action in (name for name, method in methods.items() if method.stub):
        gone = list(rejected.get(action, ()))
        if not rules.get(action) and gone:
            warnings[action] = (f"empty rule: a reviewer rejected {', '.join(map(repr, gone))} and no rule of "
                                f"{action} is left, so every call of it is allowed")
        elif action in known:
            warnings[action] = known[action]
        elif not rules.get(action):
            warnings[action] = (f"empty rule: the set has no rule for {action} (none inferred, or every one "
                                "removed), so every call of it is allowed")
    return warnings
