"""Names the gateway and the workers must agree on: queues, job ids and the Redis keys beside arq's own.

A job id is `<kind>-<sha256>` of the normalised request, so the id names its queue (GET /jobs/{id} needs no
lookup) and doubles as the cache key (identical requests share one job and one cached result).
"""

from __future__ import annotations

import hashlib
import json
import re
from functools import lru_cache
from importlib import metadata
from typing import Any, Final

from engine.settings import ModelSettings
from schemas.api import JobKind

PREFIX: Final = "precond"
MODEL_QUEUE: Final = f"{PREFIX}:queue:model"
CHECK_QUEUE: Final = f"{PREFIX}:queue:check"
MODEL_FREE_QUEUE: Final = f"{PREFIX}:queue:model-free"
"""Inference without the model (`options.generators == ["enumerate"]`): seconds, never behind model jobs,
and apart from the millisecond check jobs, which it must not hold up either."""
QUEUES: Final = (MODEL_QUEUE, MODEL_FREE_QUEUE, CHECK_QUEUE)
QUEUE_BY_KIND: Final[dict[JobKind, str]] = {
    "infer": MODEL_QUEUE,
    "next-action": MODEL_QUEUE,
    "check": CHECK_QUEUE,
}
"""The queue of each kind's model jobs; see `queue_for` for the routing by cost."""
QUEUES_BY_KIND: Final[dict[JobKind, tuple[str, ...]]] = {
    "infer": (MODEL_QUEUE, MODEL_FREE_QUEUE),
    "next-action": (MODEL_QUEUE,),
    "check": (CHECK_QUEUE,),
}
JOB_FUNCTION: Final = "run_operation"
STATS_KEY: Final = f"{PREFIX}:stats"
WORKER_PREFIX: Final = f"{PREFIX}:worker:"
WORKERS_PATTERN: Final = f"{WORKER_PREFIX}*"
RUNNING_KEY: Final = f"{PREFIX}:running"
"""Hash job id → claim (`<worker id>|<run nonce>`) of the worker running it; see jobs.heartbeats."""
UNCLAIMED_KEY: Final = f"{PREFIX}:unclaimed"
"""Hash job id → Redis time (ms) a heartbeat first saw it started (arq's in-progress key) with no claim."""
DONE_PREFIX: Final = f"{PREFIX}:done:"

_JOB_ID = re.compile(r"^(infer|next-action|check)-[0-9a-f]{64}$")


def cache_key(job_id: str) -> str:
    return f"{PREFIX}:cache:{job_id}"


def progress_key(job_id: str) -> str:
    return f"{PREFIX}:progress:{job_id}"


def done_channel(job_id: str) -> str:
    """Pub/sub channel on which a worker announces that the job's result is stored."""
    return f"{DONE_PREFIX}{job_id}"


def worker_key(worker_id: str) -> str:
    return f"{WORKER_PREFIX}{worker_id}"


def queue_for(kind: JobKind, body: dict[str, Any]) -> str:
    """Route by cost: an inference that uses no model goes to the model-free queue, so it never waits for a
    model job (minutes); everything else to its kind's queue."""
    if kind == "infer" and "model" not in body.get("options", {}).get("generators", ["model"]):
        return MODEL_FREE_QUEUE
    return QUEUE_BY_KIND[kind]


def kind_of(job_id: str) -> JobKind | None:
    """The kind a job id names, or None for ids this service never hands out."""
    match = _JOB_ID.match(job_id)
    return match.group(1) if match else None  # type: ignore[return-value]


@lru_cache(maxsize=1)
def model_identity() -> str:
    """What makes a model answer differ: the `MODEL_*` settings this deployment sets and the code version
    that loads them, as `[version, [[variable, value], ...]]`.

    `engine.settings` imports no torch, so the gateway reads the same class the workers load the model
    with; compose gives gateway and workers one environment block for this reason.
    """
    settings = ModelSettings()
    prefix = str(ModelSettings.model_config.get("env_prefix", ""))
    explicit = settings.model_dump(mode="json", include=settings.model_fields_set)
    model_env = sorted((f"{prefix}{name.upper()}", str(value)) for name, value in explicit.items())
    return json.dumps([metadata.version("precondition-service"), model_env])


def job_id(kind: JobKind, body: dict[str, Any], model: str | None) -> str:
    """Hash of the canonical JSON of kind, body (defaults filled in) and, when the job uses it, the model."""
    canonical = json.dumps(
        {"kind": kind, "body": body, "model": model},
        sort_keys=True,
        separators=(",", ":"),
        ensure_ascii=False,
    )
    return f"{kind}-{hashlib.sha256(canonical.encode()).hexdigest()}"
