"""Names the gateway and the workers must agree on: queues, job ids and every Redis key of a job's life.

A job id is `<kind>-<tenant tag>-<digest>`: the kind names its queue (GET /jobs/{id} needs no lookup), the
tenant tag names its owner (another tenant's GET or DELETE is a 404 without any lookup), and the digest is an
HMAC, keyed by the deployment's secret, of the tenant and the normalised request, so identical requests of
one tenant share one job and one cached result, and nobody without the secret can compute an id.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata
from typing import Any, Final, get_args

from arq import constants as arq_layout

from precond_client.schemas import JobKind

PREFIX: Final = "precond"
MODEL_QUEUE: Final = f"{PREFIX}:queue:model"
CHECK_QUEUE: Final = f"{PREFIX}:queue:check"
MODEL_FREE_QUEUE: Final = f"{PREFIX}:queue:model-free"
"""Inference without the model (`options.generators == ["enumerate"]`): seconds, never behind model jobs,
and apart from the millisecond check jobs, which it must not hold up either."""
TRAIN_QUEUE: Final = f"{PREFIX}:queue:train"
"""Policy training (minutes of the model's CPU): its own queue and one slot per worker, so that a training never
holds the model queue's slot and other tenants' next actions go on beside it."""
QUEUES: Final = (MODEL_QUEUE, MODEL_FREE_QUEUE, CHECK_QUEUE, TRAIN_QUEUE)
MODEL_QUEUES: Final = (MODEL_QUEUE, TRAIN_QUEUE)
"""The queues whose jobs need the code model."""
STATS_KEY: Final = f"{PREFIX}:stats"
WORKER_PREFIX: Final = f"{PREFIX}:worker:"
WORKERS_PATTERN: Final = f"{WORKER_PREFIX}*"
RUNNING_KEY: Final = f"{PREFIX}:running"
"""Hash job id → claim (`<worker id>|<run nonce>`) of the worker running it; see jobs.queue.heartbeats."""
UNCLAIMED_KEY: Final = f"{PREFIX}:unclaimed"
"""Hash job id → Redis time (ms) a heartbeat first saw it started (arq's in-progress key) with no claim."""
WAKE_PREFIX: Final = f"{PREFIX}:wake:"
STATE_TTL_S: Final = 7 * 24 * 3600
"""Lifetime of a tenant's job set and of a queue's fair scores once untouched."""

# A job's own keys keep arq's layout (`arq.constants`, its public names), where the queue's first releases kept
# them: the job's record, its in-progress mark (a worker runs it, or a cancellation guards it), its stored end,
# its try count, and the abort marks. The records under them are the project's own (payloads.py), not arq's.
JOB_PREFIX: Final[str] = arq_layout.job_key_prefix
IN_PROGRESS_PREFIX: Final[str] = arq_layout.in_progress_key_prefix
RESULT_PREFIX: Final[str] = arq_layout.result_key_prefix
RETRY_PREFIX: Final[str] = arq_layout.retry_key_prefix
ABORTS_KEY: Final[str] = arq_layout.abort_jobs_ss

TAG_CHARS: Final = 16
ID_DIGEST_CHARS: Final = 48
_JOB_ID = re.compile(
    rf"^({'|'.join(map(re.escape, get_args(JobKind)))})-([0-9a-f]{{{TAG_CHARS}}})-[0-9a-f]{{{ID_DIGEST_CHARS}}}$"
)
SHARED: Final = "shared"


def cache_key(job_id: str) -> str:
    return f"{PREFIX}:cache:{job_id}"


def progress_key(job_id: str) -> str:
    return f"{PREFIX}:progress:{job_id}"


def tenant_jobs_key(tag: str) -> str:
    """Sorted set of a tenant's unfinished jobs (its cap, `PRECOND_TENANT_MAX_JOBS`)."""
    return f"{PREFIX}:tenant:{tag}:jobs"


def fair_key(queue: str) -> str:
    """Hash tenant tag → last fair score handed out on `queue` (and `~max`, the highest)."""
    return f"{PREFIX}:fair:{queue}"


def wake_channel(queue: str) -> str:
    """Pub/sub channel on which a gateway tells idle workers that `queue` has a new job (advisory: workers
    still poll, less often)."""
    return f"{WAKE_PREFIX}{queue}"


def worker_key(worker_id: str) -> str:
    return f"{WORKER_PREFIX}{worker_id}"


class NotAJobId(ValueError):
    """An id this service never hands out (its kind, tenant tag or digest is missing or malformed)."""


@dataclass(frozen=True)
class JobId:
    """A job's identity, read once from its id and passed down as it is: its kind (which names its queue), its
    tenant's tag (its owner: every store a job writes to is that tenant's) and the id itself."""

    kind: JobKind
    tenant: str
    """The owner's tag (`tenant_tag`), never empty."""
    value: str

    def __str__(self) -> str:
        return self.value

    @classmethod
    def parse(cls, job_id: str) -> JobId:
        """The identity `job_id` names; NotAJobId for an id this service never hands out."""
        match = _JOB_ID.match(job_id)
        if match is None:
            raise NotAJobId(f"not a job id of this service: {job_id[:120]!r}")
        return cls(match.group(1), match.group(2), job_id)  # type: ignore[arg-type]

    @classmethod
    def read(cls, job_id: str) -> JobId | None:
        """`parse` for ids from a request (untrusted): None for one this service never hands out."""
        try:
            return cls.parse(job_id)
        except NotAJobId:
            return None


@lru_cache(maxsize=4096)
def tenant_tag(secret: bytes, tenant: str) -> str:
    """A tenant's name in ids and Redis keys: stable, fixed-length, and not the name itself. Kept for the
    tenants seen last: the gateway works it out for every request."""
    return hmac.new(secret, b"tenant\0" + tenant.encode(), hashlib.sha256).hexdigest()[:TAG_CHARS]


MODEL_ENV_PREFIX: Final = "MODEL_"
"""The workers' model settings (`engine.settings.ModelSettings`) are the environment variables with this
prefix, read case-insensitively and from nowhere else."""


@lru_cache(maxsize=1)
def model_identity() -> str:
    """What makes a model answer differ: the `MODEL_*` variables this deployment sets and the code version
    that loads them, as `[version, [[variable, value], ...]]`.

    Read from the environment itself, not through the workers' settings class, so that computing a job id
    loads neither the engine nor the sandbox into the gateway; compose gives gateway and workers one
    environment block for this reason. A variable the model ignores only splits the cache, never merges it.
    """
    model_env = sorted((name.upper(), value) for name, value in os.environ.items()
                       if name.upper().startswith(MODEL_ENV_PREFIX))
    return json.dumps([metadata.version("precondition-service"), model_env])


def _canonical(kind: JobKind, body: dict[str, Any], model: str | None) -> bytes:
    """Canonical JSON of kind, body (defaults filled in) and, when the job uses it, the model."""
    return json.dumps(
        {"kind": kind, "body": body, "model": model}, sort_keys=True, separators=(",", ":"), ensure_ascii=False
    ).encode()


def job_id(kind: JobKind, body: dict[str, Any], model: str | None, secret: bytes, tag: str) -> str:
    """The job of this request for the tenant whose tag (`tenant_tag`) is `tag`: identical requests of one
    tenant share it, another tenant's never does."""
    digest = hmac.new(secret, tag.encode() + b"\0" + _canonical(kind, body, model), hashlib.sha256).hexdigest()
    return f"{kind}-{tag}-{digest[:ID_DIGEST_CHARS]}"


def cache_id(kind: JobKind, body: dict[str, Any], model: str | None, secret: bytes) -> str:
    """Where a result is cached when the operator lets tenants share results: a digest of the request alone
    (otherwise a result is cached under its job id, each tenant's own)."""
    digest = hmac.new(secret, b"shared\0" + _canonical(kind, body, model), hashlib.sha256).hexdigest()
    return f"{kind}-{SHARED}-{digest[:ID_DIGEST_CHARS]}"


def is_shared(cache_id: str) -> bool:
    """Whether a result cached under `cache_id` is shared between tenants (`cache_id`, not a job id: a job id's
    middle part is a hex tenant tag)."""
    return f"-{SHARED}-" in cache_id
