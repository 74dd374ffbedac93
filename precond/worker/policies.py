"""Trained policies in the worker: a training job's adapter stored as the tenant's, and the engine of the
adapter a next action names.

A training (in a child process, `training_process`) writes its adapter into a scratch directory of this process
(mode 0700, one per job, removed when the job ends however it ends); the worker then stores the weights and what
trained them in the queue Redis (`precond/store/policies.py`) under the job's tenant. A next action naming
`adapter:<id>@<n>` is answered by an engine whose model is the served model with that adapter beside the
projections it changes, unmerged (`engine.models.backend.with_adapter`): the adapter is read under the job's
tenant, never under anything the payload says, so one tenant's job cannot reach another tenant's adapter even with
its id.
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import cache
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from precond.engine.engine import Engine
from precond.jobs.queue.keys import JobId
from precond.jobs.queue.payloads import Outcome, TrainPolicyJob
from precond.store import policies as policy_adapters
from precond.store import tenant_store
from precond.worker import training_process
from precond.worker.settings import get_worker_settings
from precond_client.schemas.errors import Conflict, InvalidInput, ModelUnavailable, NotFound
from precond_client.schemas.training import PolicyAdapter, TrainPolicyResult

ProgressFn = Callable[[str, int, int], None]
CancelledFn = Callable[[], bool]
ADAPTED_ENGINES = 16
"""Adapted models a worker keeps warm: each shares every weight of the served model and holds only its adapter,
unmerged (~2 MB for the embedded model at rank 8, `backend.with_adapter`), so 16 cost ~35 MB; their kept prompt
prefixes count against the served model's one bound (`MODEL_PREFIX_CACHE_MB`). A next action of another
adapter builds its own (a read of the adapter) in the least recently used one's place."""


@cache
def _scratch_root() -> Path:
    return Path(tempfile.mkdtemp(prefix="precond-policies-"))  # 0700, this process's own


def scratch_of(job: TrainPolicyJob) -> Path:
    """Where a training job's adapter is written: unique per job (its adapter id and version)."""
    return _scratch_root() / f"{job.adapter}-v{job.version}"


def train(engine: Engine, job: TrainPolicyJob, progress: ProgressFn, cancelled: CancelledFn) -> TrainPolicyResult:
    """What trained the adapter, which is left in `scratch_of(job)` for `keep`. The training runs in a process
    of its own (`training_process`), bounded by PRECOND_TRAINING_MAX_MEMORY_MB: the worker never holds the
    trainable copy of the model."""
    if not engine.trains:
        raise ModelUnavailable("no code model is configured for this worker")
    scratch = scratch_of(job)
    shutil.rmtree(scratch, ignore_errors=True)  # a run of this job before a restart of this process
    scratch.mkdir(mode=0o700)
    bound = get_worker_settings().training_max_memory_mb * 1024 * 1024
    return training_process.train(job.request, scratch / "adapter", progress, cancelled, bound)


def discard(body: dict[str, Any]) -> None:
    """Remove a training job's scratch directory (after it was stored, failed or was cancelled)."""
    try:
        job = TrainPolicyJob.model_validate(body)
    except ValidationError:  # never a job: nothing was written
        return
    shutil.rmtree(scratch_of(job), ignore_errors=True)


_REFUSALS = {
    tenant_store.MISSING: (NotFound, "no trained policy {id} of yours: it was deleted while this training ran"),
    tenant_store.CONFLICT: (Conflict, "trained policy {id} got version {version} from another training while this "
                            "one ran: train again to make the next version"),
    tenant_store.TOO_MANY_RECORDS: (InvalidInput, "this tenant has {max_adapters} trained policies, the bound "
                                    "(PRECOND_MAX_POLICIES_PER_TENANT): delete one first"),
    tenant_store.TOO_MANY_VERSIONS: (InvalidInput, "trained policy {id} has {max_versions} versions, the bound "
                                     "(PRECOND_MAX_POLICY_VERSIONS)"),
    tenant_store.TOO_MANY_BYTES: (InvalidInput, "this tenant's trained policies would take more than "
                                  "{max_tenant_bytes:,} bytes, the bound (PRECOND_MAX_POLICY_BYTES_PER_TENANT): "
                                  "delete one first"),
}


async def keep(redis: Any, job_id: JobId, body: dict[str, Any], result: dict[str, Any]) -> Outcome:
    """The trained adapter stored as the tenant's (its `PolicyAdapter` is the job's result), or refused at a
    bound or on a conflict; the scratch directory is removed either way."""
    from precond.engine.models.adapters import WEIGHTS  # not at import: the model code loads torch

    job, tenant = TrainPolicyJob.model_validate(body), job_id.tenant
    try:
        weights = await asyncio.to_thread((scratch_of(job) / "adapter" / WEIGHTS).read_bytes)
        adapter = PolicyAdapter(id=job.adapter, version=job.version, reference=f"{job.adapter}@{job.version}",
                                created=datetime.now(UTC).isoformat(timespec="seconds"),
                                result=TrainPolicyResult.model_validate(result))
        bounds = tenant_store.Bounds(job.max_adapters, job.max_versions, job.max_tenant_bytes)
        code = await policy_adapters.store(redis, tenant, adapter, weights, job_id.value, bounds)
    finally:
        discard(body)
    if code < 0:
        error, message = _REFUSALS[code]
        text = message.format(id=job.adapter, version=job.version, max_adapters=job.max_adapters,
                              max_versions=job.max_versions, max_tenant_bytes=job.max_tenant_bytes)
        return Outcome.failed(error(text))
    stored = await policy_adapters.get(redis, tenant, f"{job.adapter}@{code}")
    return Outcome(status="succeeded", result=(stored or adapter).model_dump(mode="json"))


@dataclass(frozen=True)
class StoredPolicy:
    tenant: str
    adapter: PolicyAdapter
    weights: bytes

    @property
    def policy(self) -> str:
        return f"adapter:{self.adapter.reference}"


async def fetch(redis: Any, tenant: str, policy: str) -> StoredPolicy:
    """The adapter version `policy` names, read under the job's `tenant`; NotFound when it is not there
    (deleted since the gateway resolved it, or never the tenant's)."""
    adapter = await policy_adapters.get(redis, tenant, policy.removeprefix("adapter:"))
    weights = await policy_adapters.weights(redis, tenant, adapter) if adapter is not None else None
    if adapter is None or weights is None:
        raise NotFound(f"no trained policy {policy.removeprefix('adapter:')[:40]} of yours", field="options.policy")
    return StoredPolicy(tenant, adapter, weights)


class AdaptedEngines:
    """The engines of the trained policies this worker served last, keyed by tenant and adapter version."""

    def __init__(self, capacity: int = ADAPTED_ENGINES) -> None:
        self.capacity = capacity
        self._engines: OrderedDict[tuple[str, str], Engine] = OrderedDict()
        self._lock = threading.Lock()

    def engine(self, base: Engine, stored: StoredPolicy) -> Engine:
        """Called in the job's thread (building merges the adapter: CPU work, under the job's memory bound)."""
        key = (stored.tenant, stored.adapter.reference)
        with self._lock:
            if key in self._engines:
                self._engines.move_to_end(key)
                return self._engines[key]
            while len(self._engines) >= self.capacity:
                self._engines.popitem(last=False)
            engine = self._engines[key] = _build(base, stored)
            return engine


def _build(base: Engine, stored: StoredPolicy) -> Engine:
    from precond.engine.models.adapters import RESULT, WEIGHTS  # not at import: the model code loads torch

    with tempfile.TemporaryDirectory(prefix="precond-adapter-") as scratch:
        directory = Path(scratch) / f"{stored.adapter.id}-v{stored.adapter.version}"
        directory.mkdir(mode=0o700)
        (directory / WEIGHTS).write_bytes(stored.weights)
        (directory / RESULT).write_text(stored.adapter.result.model_dump_json())
        return base.with_policy(directory, stored.policy)


def with_resolved_policy(body: dict[str, Any], stored: StoredPolicy) -> dict[str, Any]:
    """The next action's body naming the version it runs with (the engine answers only the policy it is)."""
    return {**body, "options": {**body.get("options", {}), "policy": stored.policy}}
