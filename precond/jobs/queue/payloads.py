"""What a queued job, a run's progress and a stored end are, as bytes: and the payloads of the jobs the gateway
makes for itself (never sent by a client, so they are not part of the public API, `precond_client.schemas`,
which ships in the client wheel, but of the wire contract between gateway and worker).

Every record is JSON, validated by a versioned pydantic model on the way in: a job (`JobRecord`), its progress
(`ProgressRecord`), its end (`EndRecord`, whose outcome is an `Outcome`). Anything with write access to the queue
Redis can put bytes where a record belongs, so a reader never runs what it reads (no pickle): bytes that fail
the schema, or carry a `version` this code does not know, raise `RecordError` naming what is wrong, and the job
ends failed with that reason (precond/worker/queue_worker.py; the gateway answers such an end as failed too).
The models' JSON Schema is exported to openapi/queue-records.schema.json (`python -m precond.cli.export`).
"""

from __future__ import annotations

from typing import Any, Final, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from precond_client.schemas import (
    ADAPTER_ID_PATTERN,
    MAX_COUNTEREXAMPLE_RUNS,
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    PRECONDITIONS_DESCRIPTION,
    SPEC_DESCRIPTION,
    Counterexamples,
    ErrorInfo,
    InferOptions,
    JobKind,
    JobProgress,
    Preconditions,
    PreconditionSet,
    StrictBody,
)
from precond_client.schemas.errors import PrecondError
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


RECORD_VERSION: Final = 1
"""The version every record is written with. A reader knows this one only: a record of another version (written
by a newer or older release) ends its job failed with that reason, never read as something else."""
MAX_REASON_CHARS: Final = 2000
"""The longest reason an end records (an exception's text, a validation error): a record's size is bounded."""


class Record(BaseModel):
    """A record's common shape: its `version`, and no field the model does not name."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    version: Literal[1] = Field(description="The record format; readers refuse any other.")


class JobRecord(Record):
    """A queued job: the operation of `kind` on `body` (validated again as the kind's payload when it runs), its
    result cached under `cache_key`."""

    kind: JobKind
    body: dict[str, Any]
    cache_key: str = Field(max_length=200)
    enqueued_ms: int = Field(ge=0, description="When the gateway enqueued it (Unix ms).")


class ProgressRecord(Record):
    """A running job's progress (advisory: the gateway shows the last one read)."""

    progress: JobProgress


class Outcome(BaseModel):
    """A finished run: the response body, or the engine's user-facing error (an input error is an outcome
    too, the client's: 422, not a crash)."""

    model_config = ConfigDict(extra="forbid")
    status: Literal["succeeded", "failed"]
    result: dict[str, Any] | None = None
    error: ErrorInfo | None = None

    @classmethod
    def failed(cls, exc: PrecondError) -> Outcome:
        """The outcome of a job the engine (or its store) refused: the error's type, message and field."""
        return cls(status="failed", error=ErrorInfo(type=exc.kind, message=exc.message, field=exc.field))


FailureReason = Literal["cancelled", "retries_exceeded", "refused", "crashed"]


class Failure(BaseModel):
    """Why a run ended without an outcome: `cancelled` (an abort), `retries_exceeded` (its workers died each
    time), `refused` (it must not run: an expired or unreadable record, an id this service never hands out),
    `crashed` (an error or a timeout of the run)."""

    model_config = ConfigDict(extra="forbid")
    reason: FailureReason
    message: str = Field(max_length=MAX_REASON_CHARS)


class EndRecord(Record):
    """A run's stored end: its `outcome` when the job returned one, else its `failure`."""

    job_id: str = Field(max_length=200)
    queue: str = Field(max_length=200)
    job_try: int = Field(ge=0, description="Which start of the job this run was (0: cancelled before any).")
    enqueued_ms: int = Field(ge=0)
    start_ms: int = Field(ge=0)
    finish_ms: int = Field(ge=0)
    outcome: Outcome | None = None
    failure: Failure | None = None

    @model_validator(mode="after")
    def _one_end(self) -> EndRecord:
        if (self.outcome is None) == (self.failure is None):
            raise ValueError("an end has an outcome or a failure, exactly one")
        return self


RECORDS: Final[tuple[type[Record], ...]] = (JobRecord, ProgressRecord, EndRecord)
"""Every record of the queue, in the exported schema's order."""


class RecordError(ValueError):
    """Bytes where a record belongs that are not one of this version: what is wrong, bounded (the bytes are
    anyone's who can write to the queue Redis)."""


R = TypeVar("R", bound=Record)


def _read(model: type[R], raw: bytes) -> R:
    try:
        return model.model_validate_json(raw)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or '(record)'}: {e['msg']}" for e in exc.errors())
        raise RecordError(f"not a version-{RECORD_VERSION} {model.__name__}: {problems}"[:MAX_REASON_CHARS]
                          ) from None


def encode_job(kind: JobKind, body: dict[str, Any], cache_key: str, enqueued_ms: int) -> bytes:
    """A job's bytes: the operation of `kind` on `body` (already validated by the gateway: not again here, a
    check's body is read on every request), its result cached under `cache_key`."""
    record = JobRecord.model_construct(version=RECORD_VERSION, kind=kind, body=body, cache_key=cache_key,
                                       enqueued_ms=enqueued_ms)
    return record.model_dump_json().encode()


def decode_job(raw: bytes) -> JobRecord:
    """A queued job's record; RecordError for anything else."""
    return _read(JobRecord, raw)


def encode_progress(progress: JobProgress) -> str:
    return ProgressRecord(version=RECORD_VERSION, progress=progress).model_dump_json()


def decode_progress(raw: bytes | None) -> JobProgress:
    """A job's progress, or none yet (also for bytes that are not a progress record: progress is advisory, and
    the job's end, read with it, says what went wrong)."""
    if not raw:
        return JobProgress()
    try:
        return _read(ProgressRecord, raw).progress
    except RecordError:
        return JobProgress()


def encode_end(end: EndRecord) -> bytes:
    return end.model_dump_json().encode()


def decode_end(raw: bytes) -> EndRecord:
    """A stored end; RecordError for anything else."""
    return _read(EndRecord, raw)


def cancelled_end(job_id: str, queue: str, now_ms: int) -> bytes:
    """The stored end of a job cancelled before any worker started it."""
    return encode_end(EndRecord(
        version=RECORD_VERSION, job_id=job_id, queue=queue, job_try=0, enqueued_ms=now_ms, start_ms=now_ms,
        finish_ms=now_ms, failure=Failure(reason="cancelled", message="the job was cancelled")))
