"""Every kind of job in one table that each dispatcher reads: everything about a kind that is data (the payload a
worker parses, the queue it goes to, whether it may run without the model, whether the worker keeps its result as
the tenant's, whether a route submits it through the gateway's `answer`, and the name of its static check).

A kind's name is the API's (`JobKind`, asserted equal to this table's keys: the client's schemas sit below this
package, so the literal cannot be derived from it). What is code about a kind lives with the layer that runs it,
keyed by this table and checked against it at import, as this package imports neither layer: what a worker runs
is its `Runner` (`precond/worker/jobs.py:RUNNERS`, one per row), what the gateway does with the body of a kind
it answers is its `Operation` (`precond/gateway/routes/operations.py:OPERATIONS`, one per row with `answered`)."""

from __future__ import annotations

from collections.abc import Iterable
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
    answered: bool = False
    """A route submits it through the gateway's one `answer` (which completes the body and screens it); the
    others are submitted by their own routes (a set's validation; a check, screened and judged where it can be in
    one trip to the check pool)."""
    static_check: str | None = None
    """The name of its programs' static check in `precond.programs.checks` that `answer` runs before queueing
    (None: none there, its route screened the request itself)."""


KINDS: Final[dict[JobKind, Kind]] = {
    "infer": Kind(InferRequest, MODEL_QUEUE, model_free=True, answered=True, static_check="check_infer_with_priors"),
    "next-action": Kind(NextActionRequest, MODEL_QUEUE, answered=True, static_check="check_next_action"),
    "check": Kind(CheckRequest, CHECK_QUEUE),
    "validate": Kind(ValidateRequest, CHECK_QUEUE),
    "reinfer": Kind(ReinferJob, MODEL_QUEUE, model_free=True, keeps=True, answered=True),
    "train-policy": Kind(TrainPolicyJob, TRAIN_QUEUE, keeps=True, answered=True, static_check="check_training"),
}
assert set(KINDS) == set(get_args(JobKind)), "every job kind of the API needs a row here"


def covers(table: str, keys: Iterable[str], wanted: Iterable[str]) -> None:
    """Raise at import when a layer's per-kind table misses a kind of this table, or names one it lacks, saying
    which: a new kind's row here is not complete until each layer that runs it has its entry."""
    have, need = set(keys), set(wanted)
    if have != need:
        raise RuntimeError(f"{table}: missing {sorted(need - have)}, not job kinds here {sorted(have - need)} "
                           "(precond/jobs/queue/kinds.py:KINDS)")


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
