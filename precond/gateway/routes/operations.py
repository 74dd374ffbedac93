"""The three operations: each becomes a job (or a cache hit), answered within the client's wait bound."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from typing import Annotated, Any, Final, Generic, TypeVar

from fastapi import APIRouter, Body, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ValidationError

from precond.convert.openai import holds_schemas
from precond.gateway import fast_check, offload
from precond.gateway.auth import CurrentCaller, bearer
from precond.gateway.caller import Caller
from precond.gateway.deps import Services, ServicesDep
from precond.gateway.errors import ServiceError, error_response, status_for
from precond.gateway.examples import openapi_examples
from precond.gateway.middleware import OffloadedBodyRoute
from precond.gateway.submission import cached_status, job_keys, submit_job
from precond.jobs.queue import keys
from precond.jobs.queue.kinds import KINDS, covers
from precond.jobs.queue.payloads import ReinferJob, TrainPolicyJob
from precond.programs import checks
from precond.store import policies as policy_adapters
from precond_client.schemas import (
    MAX_SOURCE_CHARS,
    CheckRequest,
    CheckResponse,
    ErrorInfo,
    ErrorResponse,
    InferOptions,
    InferRequest,
    InferResponse,
    JobKind,
    JobStatus,
    NextActionRequest,
    NextActionResponse,
    PriorSource,
)

router = APIRouter(tags=["operations"], route_class=OffloadedBodyRoute)

B = TypeVar("B", bound=BaseModel)
RulesRequest = TypeVar("RulesRequest", CheckRequest, NextActionRequest)
"""A request that names rules (or a stored set of them) and a history: completed alike for both kinds."""

Wait = Annotated[
    float | None,
    Query(
        ge=0, description="Seconds to wait for the result before answering 202; capped by the server's bound "
        "(`PRECOND_WAIT_MAX_S`, 30 s unless set), which a 202 states (`wait_max_s`, header `X-Wait-Max-S`)."
    ),
]
ERRORS: dict[int | str, dict[str, Any]] = {
    202: {"model": JobStatus, "description": "Not done within the wait (`?wait=`, at most `wait_max_s`, also in "
          "the `X-Wait-Max-S` header): the job runs on; poll the Location (the clients and the CLI do)."},
    400: {"model": ErrorResponse, "description": "Body is not JSON (or not UTF-8)."},
    404: {"model": ErrorResponse, "description": "`precondition_set` names no set (or version) of yours; another "
          "tenant's set is not found either."},
    413: {"model": ErrorResponse, "description": "Body larger than the configured bound."},
    401: {"model": ErrorResponse, "description": "Missing, unknown, revoked or expired API key."},
    422: {"model": ErrorResponse,
          "description": "Malformed body, input the engine cannot use, or over the work budget."},
    429: {"model": ErrorResponse,
          "description": "A limit: the tenant's request rate (`rate_limited`), its jobs queued or running "
          "(`jobs_limited`), the queue's length (`queue_full`), or failed authentications from this address "
          "(`auth_limited`); see Retry-After."},
    503: {"model": ErrorResponse, "description": "Queue backend unreachable or model unavailable."},
}


@router.post("/infer-preconditions", response_model=InferResponse, responses=ERRORS)
async def infer_preconditions(
    body: Annotated[
        InferRequest, Body(openapi_examples=openapi_examples("infer-enumerate", "infer-kept", "infer-model"))
    ],
    request: Request,
    services: ServicesDep,
    caller: CurrentCaller,
    wait: Wait = None,
) -> Response:
    """Verified preconditions per action. Demonstrations none of which calls an action are refused (422); an
    action no demonstration calls is listed in `warnings` ("no occurrence"), never a silent empty rule.
    `generators: ["enumerate"]` runs on the model-free queue, never behind model jobs."""
    return await answer(services, request, caller, "infer", body, wait)


@router.post("/next-action", response_model=NextActionResponse, responses=ERRORS)
async def next_action(
    body: Annotated[NextActionRequest, Body(openapi_examples=openapi_examples("next-action"))],
    request: Request,
    services: ServicesDep,
    caller: CurrentCaller,
    wait: Wait = None,
) -> Response:
    """The next action(s), verified against the preconditions. `options.mode` "constrained" (default): the
    sandbox judges every call the agent could make now and the model chooses among the allowed ones; when none
    is allowed, `nothing_allowed` says so (with every call in `rejected`, by the failing rule). "sample": the
    paper's Algorithm 1; when no attempt passes, `call` is null with every attempt in `rejected`, unless
    `options.fallback` is "greedy". A call is always a call of an action; a history that itself breaks the
    preconditions is answered with `history_violation` set (line and rule), not refused."""
    return await answer(services, request, caller, "next-action", body, wait)


async def check_actions(
    body: Annotated[CheckRequest, Body(openapi_examples=openapi_examples("check-actions"))],
    request: Request,
    caller: CurrentCaller,
    wait: Wait = None,
) -> Response:
    """Each call judged on its own copy of the state after the history. `allowed` is true only when the call
    ran with every rule holding; a rule or call that raises gives `allowed: false` with `error` naming the rule
    and the exception; `violations` lists the rules that do not hold. No model, never queued behind model jobs.
    A spec a converter writes with rules the restricted interpreter evaluates is judged by the gateway at once
    (`judged_by: "interpreter"`, no job); any other check runs in the sandbox (`judged_by: "sandbox"`)."""
    services: Services = request.app.state.services
    named_set = body.precondition_set is not None
    body = await _with_set(services, caller.tag, body)
    outcome = await screened_check(services, caller.tag, body)
    if isinstance(outcome, checks.Problem):
        raise _unusable(outcome)
    if isinstance(outcome, offload.Judged):
        request.scope["state"]["judged_by"] = "interpreter"  # the latency metric's label (`middleware`)
        return JSONResponse(outcome.answer)
    request.scope["state"]["judged_by"] = "sandbox"
    # a spec with its tools' schemas keeps the calls as sent: the worker checks their arguments against them
    calls = body.calls if holds_schemas(body.spec_text()) else outcome.lines
    payload = body.model_copy(update={"history": outcome.program, "calls": calls}).model_dump(mode="json")
    status = await submit_job(services, caller, "check", payload, None, wait)
    raw = await request.body()
    if status.status == "succeeded" and not named_set and len(raw) <= offload.INLINE_BODY_BYTES:
        job, cache_key = job_keys(services, caller, "check", payload, None)  # the next time, found by digest
        services.check_memo.put(caller.tag, fast_check.digest(raw), fast_check.Known(job.value, cache_key))
    return respond(request, status, services.settings.wait_max_s)


async def _cached_check(request: Request, caller: Caller, known: fast_check.Known) -> Response | None:
    """The answer of a check whose body's digest leads to its job (`fast_check`), when its result is cached:
    what `check_actions` answers for it."""
    services: Services = request.app.state.services
    status = await cached_status(services, "check", known.job_id, known.cache_key)
    if status is None:
        return None
    request.scope["state"]["judged_by"] = "sandbox"
    return respond(request, status, services.settings.wait_max_s)


class CheckRoute(OffloadedBodyRoute):
    """The check route, answered by `fast_check` where it can be, else by FastAPI's handler."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def short(request: Request) -> Response:
            body = await request.body()
            if len(body) <= offload.INLINE_BODY_BYTES:
                response = await fast_check.answer(request, body, bearer, _cached_check, check_actions)
                if response is not None:
                    return response
            return await handler(request)

        return short


router.add_api_route("/check-actions", check_actions, methods=["POST"], response_model=CheckResponse,
                     responses=ERRORS, route_class_override=CheckRoute)


async def screened_check(services: Services, tag: str,
                         body: CheckRequest) -> offload.Judged | offload.Queued | checks.Problem:
    """The check rendered, screened and, where it can be, judged, in one trip to the check pool
    (`offload.screened_check`)."""
    history = body.history if isinstance(body.history, str) else body.model_dump(include={"history"})["history"]
    calls = [c if isinstance(c, str) else c.model_dump() for c in body.calls]
    chars = _check_chars(body.spec_text(), history, calls)
    if services.settings.interpret_checks and offload.iterating_rules(body.preconditions):
        chars += offload.INLINE_CHARS  # judged in the pool, never on the loop (`offload.ITERATING`)
    return await services.checks.run(tag, chars, offload.screened_check, body.spec_text(), body.preconditions,
                                     body.decided, history, calls, tag, MAX_SOURCE_CHARS,
                                     services.settings.interpret_checks)


def _check_chars(spec: str, history: str | list[Any], calls: list[str | dict[str, Any]]) -> int:
    """What a check costs the pool, in characters of program text parsed (`CheckPool.run`)."""
    sent = len(history) if isinstance(history, str) else offload.rendering_chars("", len(json.dumps(history,
                                                                                                      default=str)))
    return len(spec) + sent + sum(len(c) if isinstance(c, str) else len(json.dumps(c)) for c in calls)


async def _with_set(services: Services, tag: str, body: RulesRequest) -> RulesRequest:
    """A stored set's spec and rules in place of its reference (404 when the tenant has no such set), its
    demonstrations too for a next action that sends none (they name the argument values the agent could use)."""
    if body.precondition_set is None:
        return body
    stored = await services.sets.get(tag, body.precondition_set)
    update: dict[str, Any] = {"spec": stored.spec, "preconditions": stored.preconditions, "precondition_set": None,
                              "decided": stored.decided}
    if isinstance(body, NextActionRequest) and not body.demonstrations:
        update["demonstrations"] = stored.demonstrations
    return body.model_copy(update=update)


async def _with_rules_and_program(
    services: Services, tag: str, body: NextActionRequest
) -> NextActionRequest | checks.Problem:
    """The request as a worker runs it: a stored set's spec and rules in place of its reference (`_with_set`),
    and a structured history (events or OpenAI messages) rendered to program text (literals only)."""
    body = await _with_set(services, tag, body)
    if not isinstance(body.history, str):
        history = body.model_dump(include={"history"})["history"]  # events and messages as plain data, at once
        chars = offload.rendering_chars(body.spec_text(), len(json.dumps(history, default=str)))
        program = await services.checks.run(tag, chars, offload.rendered, body.spec_text(), history, tag,
                                            MAX_SOURCE_CHARS)
        if isinstance(program, checks.Problem):
            return program
        body = body.model_copy(update={"history": program})
    return body


async def with_prior_sets(services: Services, tag: str, options: InferOptions) -> InferOptions:
    """The options with the tenant's stored sets named in `prior_sets` resolved to their rules (404 for a set
    that is not the tenant's), so that the worker never reads a set and the job id depends on the rules
    themselves, not on a reference whose latest version may change."""
    sources = list(options.prior_sources)
    for reference in options.prior_sets:
        stored = await services.sets.get(tag, reference)
        sources.append(PriorSource(source=stored.reference, rules=stored.preconditions))
    try:
        return InferOptions.model_validate(
            {**options.model_dump(), "prior_sets": [], "prior_sources": [s.model_dump() for s in sources]})
    except ValidationError as exc:
        raise ServiceError(422, f"options.prior_sets: {exc.errors()[0]['msg']}", "invalid_input",
                           field="options.prior_sets") from None


def _text(history: object) -> str:
    return history if isinstance(history, str) else ""


def _program_chars(body: BaseModel) -> int:
    body = body.request if isinstance(body, TrainPolicyJob) else body
    calls = [c if isinstance(c, str) else json.dumps(c.model_dump()) for c in getattr(body, "calls", [])]
    texts = [getattr(body, "spec", None) or "", _text(getattr(body, "history", "")),
             *getattr(body, "demonstrations", []), *calls]
    return sum(len(text) for text in texts)


StaticCheck = tuple[Callable[..., None], tuple[Any, ...]]
"""A static check of a request's programs (parsed, never run) and its work estimate, as a function and its
arguments for the check pool: 422 before anything is queued, not a failed job after the wait."""


@dataclass(frozen=True)
class Operation(Generic[B]):
    """What the gateway does with the body of one kind it answers before it becomes a job: complete it as a
    worker runs it, name the model its answer depends on (part of the job id), and give the arguments of its
    static check (the check itself is named by the kind's row of `KINDS`)."""

    prepare: Callable[[Services, str, B], Awaitable[B]]
    model: Callable[[B], str | None]
    check_args: Callable[[B, int, str], tuple[Any, ...]] | None
    """None where the kind's row names no static check (the route screened the request itself: a
    re-inference). Its arguments: the body, the work budget and the caller's tag (what a check may remember is
    remembered per tenant)."""


def static_check(kind: JobKind, body: BaseModel, max_work_points: int, tag: str) -> StaticCheck | None:
    """The kind's static check (named by its `KINDS` row) with its arguments from this body, or None."""
    name, args = KINDS[kind].static_check, OPERATIONS[kind].check_args
    if name is None or args is None:
        return None
    check: Callable[..., None] = getattr(checks, name)
    return check, args(body, max_work_points, tag)


async def _with_prior_sets(services: Services, tag: str, body: InferRequest) -> InferRequest:
    if not body.options.prior_sets:
        return body
    return body.model_copy(update={"options": await with_prior_sets(services, tag, body.options)})


async def _with_rules(services: Services, tag: str, body: NextActionRequest) -> NextActionRequest:
    prepared = await _with_rules_and_program(services, tag, body)
    if isinstance(prepared, checks.Problem):
        raise _unusable(prepared)
    return prepared


async def _with_rules_and_policy(services: Services, tag: str, body: NextActionRequest) -> NextActionRequest:
    """`_with_rules`, and `options.policy` naming the version it runs with (the latest for a bare id), so that
    the job id and its cached answer belong to that version: 404 when the tenant has no such trained policy."""
    body = await _with_rules(services, tag, body)
    if body.options.policy is None:
        return body
    reference = body.options.policy.removeprefix("adapter:")
    stored = await policy_adapters.get(services.redis, tag, reference)
    if stored is None:
        raise ServiceError(404, f"options.policy: no trained policy {reference} of yours (POST /policies trains "
                           "one; another tenant's is not found either)", field="options.policy")
    options = body.options.model_copy(update={"policy": f"adapter:{stored.reference}"})
    return body.model_copy(update={"options": options})


async def _as_sent(services: Services, tag: str, body: ReinferJob | TrainPolicyJob) -> ReinferJob | TrainPolicyJob:
    return body


def _model_if_generated(body: InferRequest | ReinferJob) -> str | None:
    return keys.model_identity() if "model" in body.options.generators else None


def _infer_check(body: InferRequest, max_work_points: int, _tag: str) -> tuple[Any, ...]:
    return (body.spec, body.demonstrations, body.actions, max_work_points,
            [(where, rules) for _, where, rules in body.options.priors()])


def _next_action_check(body: NextActionRequest, max_work_points: int, _tag: str) -> tuple[Any, ...]:
    return body.spec_text(), body.preconditions, body.demonstrations, _text(body.history), max_work_points


def _training_check(body: TrainPolicyJob, max_work_points: int, _tag: str) -> tuple[Any, ...]:
    return body.request.spec, body.request.demonstrations


OPERATIONS: Final[dict[JobKind, Operation[Any]]] = {
    "infer": Operation(_with_prior_sets, _model_if_generated, _infer_check),
    "next-action": Operation(_with_rules_and_policy, lambda body: keys.model_identity(), _next_action_check),
    "reinfer": Operation(_as_sent, _model_if_generated, None),
    "train-policy": Operation(_as_sent, lambda body: keys.model_identity(), _training_check),
}
"""Every kind whose `KINDS` row is `answered` (a set's validation and a check are submitted by their routes
directly: a check is screened, and judged where it can be, in one trip to the check pool)."""


def _check_rows() -> None:
    """At import: one operation per answered kind, each with check arguments exactly where its row names a
    static check, and that check a function of `precond.programs.checks`."""
    covers("precond/gateway/routes/operations.py:OPERATIONS", OPERATIONS,
           [kind for kind, row in KINDS.items() if row.answered])
    for kind, operation in OPERATIONS.items():
        name = KINDS[kind].static_check
        if (name is None) != (operation.check_args is None) or (name is not None and not hasattr(checks, name)):
            raise RuntimeError(f"OPERATIONS[{kind!r}]: its check arguments and KINDS' static_check {name!r} disagree")


_check_rows()


async def answer(
    services: Services,
    request: Request,
    caller: Caller,
    kind: JobKind,
    body: BaseModel,
    wait: float | None,
) -> Response:
    """The operation's answer: the request completed as a worker runs it, then submitted (`submit_job`), its
    programs checked statically only when it must run."""
    operation = OPERATIONS[kind]
    body = await operation.prepare(services, caller.tag, body)

    async def screen() -> None:
        found = static_check(kind, body, services.settings.max_work_points, caller.tag)
        if found is None:
            return
        check, args = found
        problem = await services.checks.run(caller.tag, _program_chars(body), offload.problem_of, check, *args)
        if problem is not None:
            if problem.type == checks.WORK_BUDGET:
                services.metrics.rejections.labels(caller.tag, "work").inc()
            raise _unusable(problem)

    payload = body.model_dump(mode="json")
    status = await submit_job(services, caller, kind, payload, operation.model(body), wait, screen)
    return respond(request, status, services.settings.wait_max_s)


def _unusable(problem: checks.Problem) -> ServiceError:
    return ServiceError(422, problem.message, problem.type, field=problem.field)


def respond(request: Request, status: JobStatus, wait_max_s: float) -> Response:
    """200 with the result, the job's error with its status, or 202 pointing at the job while it runs, saying
    the longest the server waits (a `?wait=` above it was cut to it)."""
    headers = {"X-Job-Id": status.id}
    if status.status == "succeeded":
        return JSONResponse(status.result, headers=headers)
    if status.status in ("failed", "cancelled"):
        error = status.error or ErrorInfo(type="internal", message="job failed")
        code = 409 if status.status == "cancelled" else status_for(error)
        return error_response(request, code, error, headers=headers)
    headers["Location"] = f"/jobs/{status.id}"
    headers["X-Wait-Max-S"] = f"{wait_max_s:g}"
    body = status.model_copy(update={"wait_max_s": wait_max_s}).model_dump(mode="json")
    return JSONResponse(body, status_code=202, headers=headers)
