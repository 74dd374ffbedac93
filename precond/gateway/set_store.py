"""Precondition sets: a tenant's rules, stored in the queue Redis as immutable, numbered versions.

A set is a client's data, not a cache entry: it has no TTL, lives in the queue Redis (which never evicts)
and is bounded instead: `PRECOND_MAX_SETS_PER_TENANT` sets, `PRECOND_MAX_SET_VERSIONS` versions each,
`PRECOND_MAX_SET_BYTES` per version. Keys carry the tenant, so another tenant's set is simply not
there: the same 404 as a set that never existed, without any lookup of owners.

Versions are kept by `precond/store/tenant_store.py` (the store trained policies use too) through
`precond/store/sets.py`, which a worker also uses to append the version a re-inference makes.
"""

from __future__ import annotations

import json
import re
import secrets
from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from redis.asyncio import Redis

from precond.gateway.errors import ServiceError
from precond.store import tenant_store
from precond.store.sets import decided, normal, over_bounds, put, summary, tenant_bytes_message
from precond.store.tenant_store import SETS
from precond_client.schemas import (
    CandidateReport,
    PreconditionSet,
    PreconditionSetCreate,
    PreconditionSetList,
    PreconditionSetSummary,
    RuleEdit,
    RuleEvidence,
    ValidateResponse,
)

_REFERENCE = re.compile(r"^(ps_[0-9a-f]{24})(?:@([1-9][0-9]{0,8}))?$")
_RAISED = re.compile(r"^(demonstrations\[\d+\], line \d+), args .*?: (\w+(?:Error|Exception)\b.*)$", re.DOTALL)
"""The sandbox's first violation of a rule that raised: where, then the exception."""

NOT_FOUND_HINT = (
    "a set is found only with a key of the tenant that made it; sets made while the API was open (no keys) "
    "belong to the tenant `public`: reach them with a key made by `precond keys create --tenant public` "
    "(docs/tenants.md)"
)
"""The same for every 404 of a set, whoever asks and whether or not the set exists elsewhere: it tells nothing
about other tenants' sets, and it is the first thing to check after turning keys on."""


def not_found(reference: str) -> ServiceError:
    return ServiceError(404, f"no precondition set {reference[:80]}; {NOT_FOUND_HINT}")


def parse_reference(reference: str) -> tuple[str, int | None]:
    """`id@version` or `id` (latest); anything else is a set that does not exist."""
    match = _REFERENCE.match(reference)
    if match is None:
        raise not_found(reference)
    return match.group(1), int(match.group(2)) if match.group(2) else None


PARSED_BYTES_PER_TENANT = 8 * 1024 * 1024
"""Stored JSON of the parsed versions one gateway process keeps per tenant."""


class ParsedVersions:
    """Set versions already parsed, per tenant, least recently used first out.

    A version never changes once stored, yet every check naming a set read and parsed it again on the event
    loop: 14 ms for a 550 KB version with every candidate (an SGD domain's inference with `candidates: all`).
    Bounded per tenant, so that one tenant's sets never push out another's, and so that no tenant can make
    the others' checks slower through this cache."""

    def __init__(self, max_bytes_per_tenant: int = PARSED_BYTES_PER_TENANT) -> None:
        self.max_bytes = max_bytes_per_tenant
        self._by_tenant: dict[str, OrderedDict[tuple[str, int], tuple[int, PreconditionSet]]] = {}

    def get(self, tenant: str, set_id: str, number: int) -> PreconditionSet | None:
        entries = self._by_tenant.get(tenant)
        found = None if entries is None else entries.get((set_id, number))
        if entries is None or found is None:
            return None
        entries.move_to_end((set_id, number))
        return found[1]

    def put(self, tenant: str, set_id: str, number: int, size: int, version: PreconditionSet) -> None:
        if size > self.max_bytes:
            return
        entries = self._by_tenant.setdefault(tenant, OrderedDict())
        entries[(set_id, number)] = (size, version)
        entries.move_to_end((set_id, number))
        while sum(kept for kept, _ in entries.values()) > self.max_bytes:
            entries.popitem(last=False)


class SetStore:
    def __init__(self, redis: Redis[bytes], max_sets: int, max_versions: int, max_bytes: int,
                 max_tenant_bytes: int) -> None:
        self.redis, self.max_sets, self.max_versions, self.max_bytes = redis, max_sets, max_versions, max_bytes
        self.max_tenant_bytes = max_tenant_bytes
        self.parsed = ParsedVersions()

    def refuse_oversized(self, chars: int) -> None:
        """413 before any work for a version whose texts alone pass the bound (its JSON is at least as long)."""
        if chars > self.max_bytes:
            raise ServiceError(413, f"this version would take at least {chars:,} bytes, over the bound of "
                               f"{self.max_bytes:,} (PRECOND_MAX_SET_BYTES)", field="body")

    def _record(self, version: PreconditionSet) -> str:
        text = version.model_dump_json()  # `latest` as it was then; readers replace it with the current one
        if len(text.encode()) > self.max_bytes:
            raise ServiceError(413, f"this version takes {len(text.encode()):,} bytes, over the bound of "
                               f"{self.max_bytes:,} (PRECOND_MAX_SET_BYTES)", field="body")
        return text

    def _bounds(self) -> tenant_store.Bounds:
        return tenant_store.Bounds(self.max_sets, self.max_versions, self.max_tenant_bytes)

    async def put(self, tenant: str, version: PreconditionSet) -> PreconditionSet:
        """Store version n (1: a new set) if n-1 is still the latest; the bounds' and the conflict's errors."""
        answer = await put(self.redis, tenant, version, self._record(version), self._bounds())
        if answer == tenant_store.TOO_MANY_BYTES:
            raise ServiceError(422, tenant_bytes_message(self.max_tenant_bytes), "sets_limited")
        if answer == tenant_store.TOO_MANY_RECORDS:
            raise ServiceError(422, f"this tenant stores {self.max_sets} precondition sets already, the bound "
                               "(PRECOND_MAX_SETS_PER_TENANT)", "sets_limited")
        if answer == tenant_store.MISSING:
            raise not_found(version.id)
        if answer == tenant_store.CONFLICT:
            raise ServiceError(409, f"precondition set {version.id} got a new version meanwhile: read the latest "
                               "and edit again", "conflict")
        if answer < 0:
            raise ServiceError(422, f"precondition set {version.id} has {self.max_versions} versions, the bound "
                               "(PRECOND_MAX_SET_VERSIONS): create a new set from its latest version", "sets_limited")
        return version.model_copy(update={"latest": answer})

    async def get(self, tenant: str, reference: str) -> PreconditionSet:
        """A version of one of the tenant's sets (the latest when the reference names none); 404 otherwise."""
        set_id, number = parse_reference(reference)
        latest = await tenant_store.latest(self.redis, SETS, tenant, set_id)
        if latest is None:
            raise not_found(reference)
        wanted = latest if number is None else number
        version = self.parsed.get(tenant, set_id, wanted)
        if version is None:
            raw = await tenant_store.read(self.redis, SETS, tenant, set_id, wanted)
            if raw is None:
                raise ServiceError(404, f"precondition set {set_id} has no version {wanted} (latest: {latest})")
            version = PreconditionSet.model_validate_json(raw)
            self.parsed.put(tenant, set_id, wanted, len(raw), version)
        return version.model_copy(update={"latest": latest})


    async def summaries(self, tenant: str, offset: int, limit: int) -> PreconditionSetList:
        """The tenant's sets, newest first, from each set's stored summary (never its versions, except for a set
        stored before summaries were kept: its latest version is read once here)."""
        ids = await tenant_store.ids(self.redis, SETS, tenant)
        async with self.redis.pipeline(transaction=False) as pipe:
            for set_id in ids:
                pipe.hmget(SETS.record_key(tenant, set_id), ["created", "summary"])
            rows = await pipe.execute()
        found = []
        for set_id, (created, stored) in zip(ids, rows, strict=True):
            if stored is None:
                try:
                    latest = await self.get(tenant, set_id)
                    first = latest if latest.latest == 1 else await self.get(tenant, f"{set_id}@1")
                except ServiceError:  # gone meanwhile
                    continue
                created, stored = first.created.encode(), summary(latest).encode()
            found.append(PreconditionSetSummary(created=(created or b"").decode(), **json.loads(stored)))
        found.sort(key=lambda s: (s.created, s.id), reverse=True)
        page = found[offset:offset + limit]
        more = offset + limit < len(found)
        return PreconditionSetList(sets=page, total=len(found), offset=offset, limit=limit,
                                   next_offset=offset + limit if more else None)


def new_id() -> str:
    return f"ps_{secrets.token_hex(12)}"


def now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def version_of(
    set_id: str, number: int, spec: str, preconditions: dict[str, list[str]], demonstrations: list[str],
    required: dict[str, list[str]], rejected: dict[str, list[str]], edits: list[RuleEdit],
    validation: ValidateResponse | None, warnings: dict[str, str], report: Report | None = None,
) -> PreconditionSet:
    """Version `number`; `report` is what the inference said about the rules (carried from version to version)."""
    report = report or Report()
    return PreconditionSet(
        id=set_id, version=number, latest=number, reference=f"{set_id}@{number}", created=now(), spec=spec,
        preconditions=preconditions, demonstrations=demonstrations, required=required, rejected=rejected,
        edits=edits, validation=validation, warnings=warnings, evidence=report.evidence,
        candidates=report.candidates,
        decided=_validated(decided(preconditions, report.evidence, report.candidates), validation),
    )


def _validated(labels: dict[str, dict[str, str]], validation: ValidateResponse | None) -> dict[str, dict[str, str]]:
    """A rule without an inference's evidence (written by hand) that the demonstrated calls of its action were
    judged against, none refused, is `validated`: its check is evidence too (`validation.occurrences` says how
    many calls)."""
    if validation is None:
        return labels
    refused = {f"{b.action}: {b.rule}" for b in validation.blocked} | set(validation.raised)
    return {action: {rule: "validated" if label == "no evidence" and f"{action}: {rule}" not in refused
                     and validation.occurrences.get(f"{action}: {rule}", 0) > 0 else label
                     for rule, label in rules.items()}
            for action, rules in labels.items()}


@dataclass(frozen=True)
class Report:
    """An inference's report on its rules, as a set keeps it."""

    evidence: dict[str, dict[str, RuleEvidence]] = field(default_factory=dict)
    candidates: dict[str, list[CandidateReport]] = field(default_factory=dict)
    warnings: dict[str, str] = field(default_factory=dict)

    @classmethod
    def of(cls, version: PreconditionSet | PreconditionSetCreate) -> Report:
        return cls(version.evidence, version.candidates, version.warnings)


def apply_edits(base: PreconditionSet, edits: list[RuleEdit]) -> tuple[dict[str, list[str]], dict[str, list[str]],
                                                                      dict[str, list[str]]]:
    """The rules, required and rejected rules after the edits; 422 naming `edits[i]` for one that makes no sense,
    and `edits` when the version they make would be over a bound of a request's rules (`over_bounds`)."""
    rules = {a: list(r) for a, r in base.preconditions.items()}
    required = {a: list(r) for a, r in base.required.items()}
    rejected = {a: list(r) for a, r in base.rejected.items()}

    def has(table: dict[str, list[str]], action: str, rule: str) -> bool:
        return normal(rule) in {normal(r) for r in table.get(action, [])}

    def drop(table: dict[str, list[str]], action: str, rule: str) -> None:
        """Every spelling of the rule: `x["a"]` and `x['a']` are one rule (`store.sets.normal`)."""
        if has(table, action, rule):
            table[action] = [r for r in table[action] if normal(r) != normal(rule)]
            if not table[action]:
                del table[action]

    for index, edit in enumerate(edits):
        action, rule, field = edit.action, edit.rule.strip(), f"edits[{index}]"
        present = has(rules, action, rule)
        if edit.op == "add":
            if present:
                raise ServiceError(422, f"{field}: {action} already has the rule {rule!r}", "invalid_input",
                                   field=field)
            rules.setdefault(action, []).append(rule)
            drop(rejected, action, rule)  # adding by hand overrides an earlier rejection
        elif edit.op == "require":
            if not present:
                raise ServiceError(422, f"{field}: {action} has no rule {rule!r} to require (add it first)",
                                   "invalid_input", field=field)
            if not has(required, action, rule):
                required.setdefault(action, []).append(rule)
        else:  # remove, reject
            if not present and edit.op == "remove":
                raise ServiceError(422, f"{field}: {action} has no rule {rule!r} to remove", "invalid_input",
                                   field=field)
            drop(rules, action, rule)
            drop(required, action, rule)
            if edit.op == "reject" and not has(rejected, action, rule):
                rejected.setdefault(action, []).append(rule)
    problem = over_bounds(rules)
    if problem is not None:
        raise ServiceError(422, f"edits: {problem}", "invalid_input", field="edits")
    return rules, required, rejected


MAX_NAMED = 8
"""Demonstrations a blocking message names; the error's `blocked` lists every call."""


def blocking_message(validation: ValidateResponse, new_rules: set[tuple[str, str]]) -> tuple[str, Any] | None:
    """Why an edit is refused: the first new rule that blocks a demonstrated call, the demonstrations the new
    rules block, and the ways out."""
    blocked = [b for b in validation.blocked if (b.action, b.rule) in new_rules]
    if not blocked:
        return None
    raising = [b for b in blocked if f"{b.action}: {b.rule}" in validation.raised]
    if raising:  # a typo (`self.user.afirmed`) is an exception to name, not calls to count
        first = raising[0]
        error = validation.raised[f"{first.action}: {first.rule}"]
        found = _RAISED.match(error)
        where, exception = found.groups() if found else ("", error)
        count = sum((b.action, b.rule) == (first.action, first.rule) for b in blocked)
        message = (f"rule {first.rule!r} of {first.action} raises {exception}" + (f" ({where})" if where else "")
                   + f" instead of answering true or false, so it refuses every call it raises at ({count} "
                   "demonstrated call(s)): fix the rule (a misspelt name?), or send force: true to keep it anyway")
        return message, first
    first = blocked[0]
    more = len(blocked) - 1
    demos = sorted({b.demonstration for b in blocked})
    named = ", ".join(f"demonstrations[{d}]" for d in demos[:MAX_NAMED]) + (
        f" and {len(demos) - MAX_NAMED} more" if len(demos) > MAX_NAMED else "")
    message = (f"rule {first.rule!r} of {first.action} would have blocked demonstrations[{first.demonstration}], "
               f"line {first.line} ({first.call})" + (f", and {more} more demonstrated call(s)" if more else "")
               + f"; the new rules block {named} (every call: the error's `blocked`). Ways out: fix the rule; send "
               "force: true to keep it anyway (the calls it blocks become its known exceptions: right when they "
               "are calls to refuse, such as labelled ones); store the set without it (or reject it in an edit); "
               "or leave those demonstrations out")
    return message, first
