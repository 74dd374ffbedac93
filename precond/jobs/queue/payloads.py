"""What a queued job and a stored end are, as bytes: and the payloads of the jobs the gateway makes for itself
(never sent by a client, so they are not part of the public API, `precond_client.schemas.api`, which ships in the
client wheel, but of the wire contract between gateway and worker).

A job is stored as arq's job record (`arq.jobs.serialize_job`: function name, arguments, enqueue time) with one
function, `run_operation(kind, body, cache_key)`; an end as arq's result record (`arq.jobs.serialize_result`). Both
through arq's public serialisation functions, so that `arq.jobs.Job` reads them.
"""

from __future__ import annotations

import asyncio
from typing import Any

from arq.jobs import JobResult, deserialize_result, serialize_job, serialize_result
from pydantic import Field

from precond.jobs.queue.keys import JOB_FUNCTION
from precond_client.schemas.api import (
    ADAPTER_ID_PATTERN,
    MAX_COUNTEREXAMPLE_RUNS,
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    PRECONDITIONS_DESCRIPTION,
    SPEC_DESCRIPTION,
    Counterexamples,
    InferOptions,
    JobKind,
    Preconditions,
    PreconditionSet,
    StrictBody,
)
from precond_client.schemas.training import TrainPolicyRequest


class ValidateRequest(StrictBody):
    """A worker job (kind `validate`, on the check queue): which demonstrated calls each rule would block.
    The gateway sends it for every new version of a precondition set that has demonstrations."""

    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    preconditions: Preconditions = Field(default_factory=dict, description=PRECONDITIONS_DESCRIPTION)
    demonstrations: list[str] = Field(min_length=1, max_length=MAX_DEMONSTRATIONS)


class ReinferJob(StrictBody):
    """A worker job (kind `reinfer`): infer on the base version's spec with its stored demonstrations and the
    new ones, merge with its required and rejected rules, validate, and store the result as the next version
    (the gateway resolved the base; the worker appends only if it is still the latest)."""

    base: PreconditionSet
    demonstrations: list[str] = Field(max_length=MAX_DEMONSTRATIONS)
    counterexamples: list[Counterexamples] = Field(
        default_factory=list, max_length=MAX_COUNTEREXAMPLE_RUNS,
        description="New labelled calls, stored with the version after the base's (which the inference also uses).")
    actions: list[str] | None = None
    options: InferOptions = Field(default_factory=InferOptions)
    force: bool = False
    max_versions: int = Field(ge=1)
    max_bytes: int = Field(ge=1)
    max_tenant_bytes: int | None = Field(default=None, ge=1, description="Bytes of all the tenant's sets; None: "
                                         "unbounded (a job queued by a gateway that did not send it).")


class TrainPolicyJob(StrictBody):
    """A worker job (kind `train-policy`): train on `request` and store the adapter as version `version` of the
    tenant's adapter `adapter` (version 1: a new one), within the bounds the gateway sent (the worker's store
    enforces them atomically; the gateway only refuses early)."""

    request: TrainPolicyRequest
    adapter: str = Field(pattern=f"^{ADAPTER_ID_PATTERN}$")
    version: int = Field(ge=1)
    max_adapters: int = Field(ge=1)
    max_versions: int = Field(ge=1)
    max_tenant_bytes: int = Field(ge=1)


def encode_job(kind: JobKind, body: dict[str, Any], cache_key: str, enqueued_ms: int) -> bytes:
    """A job's bytes: the operation of `kind` on `body`, its result cached under `cache_key`."""
    return serialize_job(JOB_FUNCTION, (kind, body, cache_key), {}, None, enqueued_ms)


def encode_end(job_id: str, queue: str, job: tuple[str, tuple[Any, ...], int], job_try: int, success: bool,
               result: Any, start_ms: int, finish_ms: int) -> bytes | None:
    """A run's stored end: `job` is the run's (function name, arguments, enqueue time); `result` the outcome, or
    the exception that ended it. None when it cannot be serialised (arq logs why)."""
    function, args, enqueued_ms = job
    return serialize_result(function, args, {}, job_try, enqueued_ms, success, result, start_ms, finish_ms,
                            f"{job_id}:{function}", queue, job_id)


def cancelled_end(job_id: str, queue: str, kind: JobKind, now_ms: int) -> bytes | None:
    """The stored end of a job cancelled before any worker started it."""
    return encode_end(job_id, queue, (JOB_FUNCTION, (kind,), now_ms), 0, False, asyncio.CancelledError(), now_ms,
                      now_ms)


def decode_end(raw: bytes) -> JobResult:
    return deserialize_result(raw)
