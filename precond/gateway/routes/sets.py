"""Precondition sets: create, read any version, edit by making a new version (checked against the demonstrations
by a worker: the gateway never runs code). Another tenant's set is a 404, word for word as a missing one."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import JSONResponse, Response

from precond.gateway import offload
from precond.gateway.auth import RATE_LIMITED, CurrentCaller
from precond.gateway.caller import Caller
from precond.gateway.deps import Services, ServicesDep
from precond.gateway.errors import ServiceError, status_for
from precond.gateway.middleware import OffloadedBodyRoute
from precond.gateway.routes.operations import ERRORS, Wait, answer, with_prior_sets
from precond.gateway.set_store import Report, apply_edits, blocking_message, new_id, not_found, version_of
from precond.gateway.submission import submit_job
from precond.jobs.queue.payloads import ReinferJob, ValidateRequest
from precond.programs import checks
from precond.store.sets import check_set, normal, set_warnings, union
from precond_client.schemas import (
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    MAX_SOURCE_NAME_CHARS,
    Counterexamples,
    ErrorInfo,
    ErrorResponse,
    LabelledCall,
    PreconditionSet,
    PreconditionSetCreate,
    PreconditionSetEdit,
    PreconditionSetList,
    PreconditionSetReinfer,
    SetCounterexample,
    ValidateResponse,
)

router = APIRouter(prefix="/precondition-sets", tags=["precondition sets"], route_class=OffloadedBodyRoute)
RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorResponse, "description": "Body is not JSON (or not UTF-8)."},
    401: {"model": ErrorResponse, "description": "Missing, unknown, revoked or expired API key."},
    404: {"model": ErrorResponse, "description": "No such set (or version) of yours: another tenant's set is not "
          "found either."},
    409: {"model": ErrorResponse, "description": "`base_version` is no longer the latest version."},
    413: {"model": ErrorResponse, "description": "A version over PRECOND_MAX_SET_BYTES."},
    422: {"model": ErrorResponse, "description": "Malformed body or rule (field names it, e.g. `edits[2]`), a rule "
          "that would block a demonstrated call (unless `force`), or over a bound (`sets_limited`)."},
    429: {"model": ErrorResponse, "description": "A limit of the tenant (request rate, jobs), of failed "
          "authentications from this address, or of the check queue (see Retry-After)."},
    503: {"model": ErrorResponse, "description": "Queue backend unreachable, or the check against the "
          "demonstrations did not finish in time (retry: its result is cached)."},
}
SetReference = Annotated[str, Path(max_length=100, description="`id`, or `id@version`.")]
SetId = Annotated[str, Path(max_length=100)]
MAX_LISTED_SETS = 100
NO_RULES = (
    "no rules: a set is made of rules, and one without any would allow every call of every action. To learn them "
    "from these demonstrations, POST this `spec` and `demonstrations` to /infer-preconditions (or `precond infer`), "
    "then create the set from its answer's `preconditions`, `evidence`, `candidates` and `warnings` (the review "
    "page's \"New set from request.json\" does both); or write rules by hand: {\"SYSTEM.INFORM\": "
    "[\"self.user.requested_slot[slot]\"]}")


@router.post("", response_model=PreconditionSet, status_code=201, responses=RESPONSES)
async def create_set(body: PreconditionSetCreate, services: ServicesDep, caller: CurrentCaller) -> JSONResponse:
    """Store rules as version 1 of a new set, by hand or from an inference (its `preconditions`, with the `spec`
    and `demonstrations` it was inferred from). Rules that would block a demonstrated call are refused (422,
    naming the rule and the demonstration) unless `force`; the report is kept in `validation`. A body without
    any rule is refused (422 saying how to learn them): such a set would allow every call of every action."""
    if not any(body.preconditions.values()):
        raise ServiceError(422, NO_RULES, "invalid_input", field="preconditions")
    rules = await _static_check(services, caller, body.spec, body.preconditions, body.demonstrations)
    validation = await _validate(services, caller, body.spec, rules, body.demonstrations)
    _refuse_blocking(validation, {(a, r) for a, rs in rules.items() for r in rs}, body.force, "preconditions")
    set_id = new_id()
    report = Report.of(body)
    warnings = set_warnings(body.spec, rules, {}, report.warnings)
    version = version_of(set_id, 1, body.spec, rules, body.demonstrations, {}, {}, [], validation, warnings,
                         report)
    stored = await services.sets.put(caller.tag, version)
    return JSONResponse(stored.model_dump(mode="json"), status_code=201)


@router.get("", response_model=PreconditionSetList, responses={
    401: RESPONSES[401], 422: {"model": ErrorResponse, "description": "`offset` or `limit` out of range."},
    429: RATE_LIMITED})
async def list_sets(services: ServicesDep, caller: CurrentCaller,
                    offset: Annotated[int, Query(ge=0, le=10**6)] = 0,
                    limit: Annotated[int, Query(ge=1, le=MAX_LISTED_SETS)] = 20) -> PreconditionSetList:
    """The tenant's sets, newest first: per set its latest version, actions, and how many rules are `assumed`,
    `zero-shot` or without evidence (the ones a human should read). `next_offset` pages on."""
    return await services.sets.summaries(caller.tag, offset, limit)


@router.get("/{reference}", response_model=PreconditionSet, responses=RESPONSES)
async def get_set(reference: SetReference, services: ServicesDep, caller: CurrentCaller) -> Response:
    """The latest version (`id`) or a given one (`id@version`)."""
    return _as_json(await services.sets.get(caller.tag, reference))


@router.get("/{set_id}/versions/{number}", response_model=PreconditionSet, responses=RESPONSES)
async def get_version(set_id: SetId, number: Annotated[int, Path(ge=1, le=10**9)], services: ServicesDep,
                      caller: CurrentCaller) -> Response:
    return _as_json(await services.sets.get(caller.tag, f"{set_id}@{number}"))


def _as_json(version: PreconditionSet) -> Response:
    """Serialised by pydantic at once: a version with an inference's candidates is hundreds of KB, and FastAPI's
    re-validation and generic encoding of a returned model took 35 ms of the review page's 300."""
    return Response(version.model_dump_json(), media_type="application/json")


@router.post("/{set_id}/versions", response_model=PreconditionSet, status_code=201, responses=RESPONSES)
async def edit_set(set_id: SetId, body: PreconditionSetEdit, services: ServicesDep,
                   caller: CurrentCaller) -> JSONResponse:
    """A new version from the latest by edits: `add` a rule, `remove` one, `require` one, `reject` one (removed,
    and kept out of re-inference). The new rules are checked against the set's demonstrations in the sandbox;
    one that would block a demonstrated call is refused (422 naming the rule and the demonstration) unless
    `force`. Earlier versions stay as they were."""
    tag = caller.tag
    base = await _latest(services, tag, set_id, body.base_version)
    rules, required, rejected = apply_edits(base, body.edits)
    rules = await _static_check(services, caller, base.spec, rules, [], field="edits")
    before = {(a, r) for a, rs in base.preconditions.items() for r in rs}
    new = {(a, r) for a, rs in rules.items() for r in rs} - before
    validation = await _validate(services, caller, base.spec, rules, base.demonstrations)
    _refuse_blocking(validation, new, body.force, "edits")
    edited = {edit.action for edit in body.edits}
    known = {action: warning for action, warning in base.warnings.items() if action not in edited}
    version = version_of(set_id, base.latest + 1, base.spec, rules, base.demonstrations, required, rejected,
                         body.edits, validation, set_warnings(base.spec, rules, rejected, known), Report.of(base)
                         ).model_copy(update={"counterexamples": base.counterexamples})
    stored = await services.sets.put(tag, version)
    return JSONResponse(stored.model_dump(mode="json"), status_code=201)


REINFER_RESPONSES: dict[int | str, dict[str, Any]] = {
    **RESPONSES, 202: ERRORS[202],
    409: {"model": ErrorResponse, "description": "`base_version` is not the latest version, or the set got a new "
          "version while the re-inference ran (`conflict`)."},
    422: {"model": ErrorResponse, "description": "Malformed body or demonstration (field names it, e.g. "
          "`demonstrations[2]`), a new demonstration that a required rule would block (`blocks_demonstration`, "
          "unless `force`), over a bound (`sets_limited`, `work_budget`)."},
    429: ERRORS[429], 503: ERRORS[503],
}


@router.post("/{set_id}/reinfer", response_model=PreconditionSet, responses=REINFER_RESPONSES)
async def reinfer_set(set_id: SetId, body: PreconditionSetReinfer, request: Request, services: ServicesDep,
                      caller: CurrentCaller, wait: Wait = None) -> Response:
    """Re-infer the set's rules from its stored demonstrations and new ones (a job, like `/infer-preconditions`:
    200 with the new version when done within `wait`, else 202 and `/jobs/{id}`). The new version keeps every
    rule marked *required* (refused, 422 naming the new demonstration and line, when a new demonstration breaks
    one, unless `force`), never brings back a rule marked *rejected*, stores the union of the demonstrations,
    and carries `diff` against its base: rules `added`, `removed` (each with why it was dropped), `kept`,
    `required_kept`, `rejected_suppressed`."""
    tag = caller.tag
    base = await _latest(services, tag, set_id, body.base_version)
    demonstrations = union(base.demonstrations, body.demonstrations)
    if len(demonstrations) > MAX_DEMONSTRATIONS:
        raise ServiceError(422, f"the set's {len(base.demonstrations)} demonstrations and these would be "
                           f"{len(demonstrations)}, over {MAX_DEMONSTRATIONS}", "invalid_input",
                           field="demonstrations")
    options = await with_prior_sets(services, tag, body.options) if body.options.prior_sets else body.options
    chars = len(base.spec) + sum(map(len, demonstrations))
    services.sets.refuse_oversized(chars)
    problem = await services.checks.run(tag, chars, offload.problem_of, checks.check_reinfer, base.spec,
                                        body.demonstrations, demonstrations, body.actions,
                                        services.settings.max_work_points)
    if problem is not None:
        field = problem.field if problem.field.startswith(("actions", "demonstrations[")) else "demonstrations"
        raise ServiceError(422, problem.message, problem.type, field=field)
    job = ReinferJob(base=base, demonstrations=body.demonstrations, actions=body.actions, options=options,
                     force=body.force,
                     max_versions=services.settings.max_set_versions, max_bytes=services.settings.max_set_bytes,
                     max_tenant_bytes=services.settings.max_set_bytes_per_tenant)
    return await answer(services, request, caller, "reinfer", job, wait)


@router.post("/{set_id}/counterexamples", response_model=PreconditionSet, responses=REINFER_RESPONSES)
async def add_counterexample(set_id: SetId, body: SetCounterexample, request: Request, services: ServicesDep,
                             caller: CurrentCaller, wait: Wait = None) -> Response:
    """A judged call that should have been refused (or allowed), kept with the set: its history and call become a
    run of their own (rendered and checked as `/check-actions` does, never run here), and the set is re-inferred
    for the call's action (a job, as `/reinfer`) with every counterexample the set keeps and this one. The new
    version stores them all, and each rule's `evidence[...].refuses` names the ones it refuses. At most
    PRECOND_MAX_SET_COUNTEREXAMPLES per set (422 `sets_limited`)."""
    tag, limit = caller.tag, services.settings.max_set_counterexamples
    base = await _latest(services, tag, set_id, body.base_version)
    if len(base.counterexamples) >= limit:
        raise ServiceError(422, f"precondition set {set_id} keeps {len(base.counterexamples)} counterexamples, the "
                           f"bound of {limit} (PRECOND_MAX_SET_COUNTEREXAMPLES): create a new set from its latest "
                           "version", "sets_limited", field="call")
    sent = body.model_dump(include={"history", "call"})  # events, messages and tool calls as plain data
    chars = offload.rendering_chars(base.spec, len(json.dumps(sent, default=str)))
    made = await services.checks.run(tag, chars, offload.labelled_run, base.spec, sent["history"], sent["call"], tag,
                                     MAX_SOURCE_CHARS)
    if isinstance(made, checks.Problem):
        raise ServiceError(422, made.message, made.type, field=made.field)
    program, line, action = made
    _refuse_labelled_already(base.counterexamples, program, line, body.verdict)
    name = f"review {len(base.counterexamples) + 1}: {program.splitlines()[-1].strip()}"[:MAX_SOURCE_NAME_CHARS]
    labelled = Counterexamples(program=program, calls=[LabelledCall(line=line, verdict=body.verdict, name=name)])
    actions = body.actions or [action]
    options = await with_prior_sets(services, tag, body.options) if body.options.prior_sets else body.options
    chars = len(base.spec) + sum(map(len, base.demonstrations)) + len(program) + sum(
        len(run.program or "") for run in base.counterexamples)
    services.sets.refuse_oversized(chars)
    problem = await services.checks.run(tag, chars, offload.problem_of, checks.check_reinfer, base.spec, [],
                                        base.demonstrations, actions, services.settings.max_work_points)
    if problem is not None:
        raise ServiceError(422, problem.message, problem.type, field="actions" if problem.field.startswith(
            "actions") else f"base.{problem.field}")
    job = ReinferJob(base=base, demonstrations=[], counterexamples=[labelled], actions=actions, options=options,
                     force=body.force,
                     max_versions=services.settings.max_set_versions, max_bytes=services.settings.max_set_bytes,
                     max_tenant_bytes=services.settings.max_set_bytes_per_tenant)
    return await answer(services, request, caller, "reinfer", job, wait)


def _refuse_labelled_already(kept: list[Counterexamples], program: str, line: int, verdict: str) -> None:
    """One history and call is labelled once: again the same way adds nothing, the other way contradicts the
    set's label (the inference would refuse both); 422 naming the stored one either way."""
    lines = program.splitlines()
    for i, run in enumerate(kept):
        mine = (run.program or "").splitlines()
        for call in run.calls:
            if call.line == line and mine[:line] == lines[:line]:
                how = "already" if call.verdict == verdict else f"the other way ({call.verdict!r}): it is"
                raise ServiceError(422, f"this history and call are {how} labelled as base.counterexamples[{i}] "
                                   f"({call.name})", "invalid_input", field="call")


async def _latest(services: Services, tag: str, set_id: str, base_version: int | None) -> PreconditionSet:
    """The set a new version builds on: a bare id (a version reference is 404), whose latest version must be
    `base_version` when the caller names one (optimistic concurrency: otherwise 409)."""
    if "@" in set_id:
        raise not_found(set_id)
    base = await services.sets.get(tag, set_id)
    if base_version is not None and base_version != base.latest:
        raise ServiceError(409, f"base_version {base_version} is not the latest version ({base.latest})",
                           "conflict")
    return base


async def _static_check(services: Services, caller: Caller, spec: str, rules: dict[str, list[str]],
                        demonstrations: list[str], field: str | None = None) -> dict[str, list[str]]:
    """Parsed, never run: the spec, every rule (known action, one expression, within the embedded guard's bounds
    whatever the state: `precondition_sets.check_rule_work`) and the demonstrations; after the size bound (413
    before any parse), in the check pool when large (parsing holds the event loop)."""
    chars = len(spec) + sum(map(len, demonstrations)) + sum(len(r) for rs in rules.values() for r in rs)
    services.sets.refuse_oversized(chars)
    problem = await services.checks.run(caller.tag, chars, offload.problem_of, check_set, spec,
                                        rules, demonstrations)
    if problem is not None:
        raise ServiceError(422, problem.message, problem.type, field=field or problem.field)
    return {action: _unique(rs) for action, rs in rules.items() if rs}


def _unique(rules: list[str]) -> list[str]:
    """Each rule once, however it is spelled (`x["a"]` is `x['a']`: `store.sets.normal`), as first
    written."""
    first: dict[str, str] = {}
    for rule in rules:
        first.setdefault(normal(rule), rule.strip())
    return list(first.values())


def _refuse_blocking(validation: ValidateResponse | None, new: set[tuple[str, str]], force: bool, field: str) -> None:
    if validation is None or force:
        return
    refusal = blocking_message(validation, new)
    if refusal is not None:
        raise ServiceError(422, refusal[0], "blocks_demonstration", field=field,
                           blocked=[b for b in validation.blocked if (b.action, b.rule) in new])


async def _validate(services: Services, caller: Caller, spec: str, rules: dict[str, list[str]],
                    demonstrations: list[str]) -> ValidateResponse | None:
    """The rules judged against the demonstrations by a worker (a `validate` job on the check queue)."""
    if not demonstrations or not rules:
        return None
    payload = ValidateRequest(spec=spec, preconditions=rules, demonstrations=demonstrations).model_dump(mode="json")
    status = await submit_job(services, caller, "validate", payload, None, None)
    if status.status in ("queued", "running"):
        raise ServiceError(503, "the check of the rules against the demonstrations did not finish in time; retry "
                           "(its result is kept)", headers={"Retry-After": str(services.settings.retry_after_s)})
    if status.status != "succeeded" or status.result is None:
        error = status.error or ErrorInfo(type="internal", message="the check against the demonstrations failed")
        raise ServiceError(status_for(error), error.message, error.type, field=error.field)
    return ValidateResponse.model_validate(status.result)
