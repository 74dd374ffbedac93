"""Every kind of job in one table that each dispatcher reads: the payload a worker parses, the queue it goes
to, whether it may run without the model, and whether the worker keeps its result as the tenant's.

A kind's name is the API's (`JobKind`, asserted equal to this table's keys); what a worker runs for it is its row
of `precond/worker/jobs.py:RUNNERS` (checked against this table at import) and, for a kind a route submits through
the gateway's one `answer`, what the gateway does with its body first is its row of
`precond/gateway/routes/operations.py:OPERATIONS`: those layers' own tables, as this package imports neither."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final, get_args

from pydantic import BaseModel

from precond.jobs.queue.keys import CHECK_QUEUE, MODEL_FREE_QUEUE, MODEL_QUEUE, TRAIN_QUEUE
from precond.jobs.queue.payloads import ReinferJob, TrainPolicyJob, ValidateRequest
from precond_client.schemas import CheckRequest, InferRequest, JobKind, NextActionRequest


@dataclass(frozen=True)
class Kind:
    payload: type[BaseModel]
    queue: str
    """Where its jobs go (those that use the model, for a kind that may run without it)."""
    model_free: bool = False
    """Whether a job may leave the model out (`options.generators` without "model"): it then goes to the
    model-free queue, so that it never waits behind model jobs (minutes)."""
    keeps: bool = False
    """The worker keeps the result as the tenant's (a precondition set's next version, a trained policy): never
    shared between tenants."""


KINDS: Final[dict[JobKind, Kind]] = {
    "infer": Kind(InferRequest, MODEL_QUEUE, model_free=True),
    "next-action": Kind(NextActionRequest, MODEL_QUEUE),
    "check": Kind(CheckRequest, CHECK_QUEUE),
    "validate": Kind(ValidateRequest, CHECK_QUEUE),
    "reinfer": Kind(ReinferJob, MODEL_QUEUE, model_free=True, keeps=True),
    "train-policy": Kind(TrainPolicyJob, TRAIN_QUEUE, keeps=True),
}
assert set(KINDS) == set(get_args(JobKind)), "every job kind of the API needs a row here"


def queue_for(kind: JobKind, body: dict[str, Any]) -> str:
    """Route by cost: an inference that uses no model goes to the model-free queue; everything else to its
    kind's queue."""
    row = KINDS[kind]
    if row.model_free and "model" not in body.get("options", {}).get("generators", ["model"]):
        return MODEL_FREE_QUEUE
    return row.queue


def tenant_private(kind: JobKind, body: dict[str, Any]) -> bool:
    """Whether the result is the tenant's alone, never a shared cache entry even where the operator shares
    results: what it stores, and a next action of the tenant's own trained policy."""
    row = KINDS[kind]
    return row.keeps or bool(body.get("options", {}).get("policy"))


def queues_of(kind: JobKind) -> tuple[str, ...]:
    """Every queue a job of this kind may be in."""
    row = KINDS[kind]
    return (row.queue, MODEL_FREE_QUEUE) if row.model_free else (row.queue,)
