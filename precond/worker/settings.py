"""The queue worker's settings (`PRECOND_*`), read once per process."""

from __future__ import annotations

from functools import lru_cache

from pydantic import Field, field_validator, model_validator

from precond.jobs.queue.keys import MODEL_QUEUE, QUEUES, TRAIN_QUEUE
from precond.jobs.settings import QueueSettings


def queue_names(value: str) -> list[str]:
    """The queues a comma list names, each once, in the list's order; ValueError naming the first unknown one."""
    names = list(dict.fromkeys(name.strip() for name in value.split(",") if name.strip()))
    unknown = [name for name in names if name not in QUEUES]
    if unknown:
        raise ValueError(f"PRECOND_WORKER_QUEUES: no queue is named {unknown[0]!r}; the queues are {', '.join(QUEUES)}")
    if not names:
        raise ValueError(f"PRECOND_WORKER_QUEUES names no queue; the queues are {', '.join(QUEUES)}")
    return names


class WorkerSettings(QueueSettings):
    """The queue worker (`precond/worker/`): a worker loop per queue, heartbeats, draining."""

    job_timeout_s: float = Field(
        default=900.0,
        gt=0,
        description="Longest a model job or a model-free inference may run. (A job whose worker died is handed "
        "to another worker once the dead worker's heartbeat expires, not after this timeout.)",
    )
    max_response_bytes: int = Field(
        default=8 * 1024 * 1024, ge=1024,
        description="Largest answer a job may return; above it the job fails with `response_too_large` (422).",
    )
    check_timeout_s: float = Field(default=60.0, gt=0, description="Longest a check-actions job may run.")
    job_max_memory_mb: int = Field(
        default=1024, ge=64,
        description="How much a job may grow the worker's own resident memory (what the engine builds there, "
        "outside the sandbox's limits) over its size when the job started; above it the job fails alone "
        "(`resource_limit`, 422) and the worker goes on. With `PRECOND_PRELOAD_MODEL=false`, set it above the "
        "model's size (the first model job loads it).",
    )
    training_max_memory_mb: int = Field(
        default=4096, ge=64,
        description="Largest resident size of a policy training's process: a worker trains in a child process of "
        "its own (it loads a trainable float32 copy of the model, ~2 GB for the embedded one, and "
        "backpropagates through it), never in the worker itself; a child above this is killed and the job fails "
        "(`resource_limit`, 422). The worker's own bound stays PRECOND_JOB_MAX_MEMORY_MB.",
    )
    job_max_tries: int = Field(
        default=3, ge=1, description="Runs of a job before it fails (worker deaths count)."
    )
    worker_queues: str = Field(
        default=",".join(QUEUES),
        description=f"The queues this worker reads, a comma list of {', '.join(f'`{q}`' for q in QUEUES)} "
        f"(`precond worker --queues`). A worker without `{MODEL_QUEUE}` never loads the code model itself: one that "
        f"reads only `{TRAIN_QUEUE}` trains policies, each in a process of its own "
        "(PRECOND_TRAINING_MAX_MEMORY_MB), and the others stay small (docs/deploy.md splits them so).",
    )
    worker_concurrency: int = Field(
        default=1,
        ge=1,
        description="Model jobs one worker process runs at once; as many model-free inferences (their own "
        "queue, so they never wait behind model jobs) run beside them.",
    )
    check_concurrency: int = Field(default=4, ge=1, description="check-actions jobs one worker runs at once.")
    tenant_max_running: int | None = Field(
        default=None, ge=1,
        description="Jobs of one tenant one worker runs at once on each queue, so that the rest of its slots "
        "stay for the other tenants (fair order decides who goes next, but reserves nothing). Unset: half the "
        "queue's concurrency, at least 1.",
    )
    worker_poll_s: float = Field(
        default=0.1, gt=0, description="How often an idle worker reads the model and training queues while it "
        "cannot hear new-job notices (its subscription is down; a gateway publishes one with every job it "
        "enqueues). While it can, it reads them every second, and at once on a notice."
    )
    check_poll_s: float = Field(
        default=0.01,
        gt=0,
        description="How often an idle worker reads the check and model-free queues while it cannot hear new-job "
        "notices (its subscription is down): what a lost notice adds to a check's latency then. While it can, "
        "it reads them every second, and at once on a notice.",
    )
    drain_s: int = Field(
        default=30, ge=0, description="On SIGTERM, how long a worker lets running jobs finish."
    )
    heartbeat_s: float = Field(default=2.0, gt=0, description="Worker heartbeat period.")
    heartbeat_ttl_s: float | None = Field(
        default=None,
        gt=0,
        description="How long a worker's heartbeat lives: a worker silent this long is dead, and the jobs it "
        "was running are handed to live workers at their next heartbeat. Unset: 3 × `PRECOND_HEARTBEAT_S`.",
    )
    preload_model: bool = Field(
        default=True, description="Load the model when the worker starts (else lazily)."
    )

    @field_validator("worker_queues")
    @classmethod
    def _known_queues(cls, value: str) -> str:
        return ",".join(queue_names(value))

    @property
    def queues(self) -> list[str]:
        """The queues this worker reads (`PRECOND_WORKER_QUEUES`)."""
        return self.worker_queues.split(",")

    @model_validator(mode="after")
    def _ttl_outlives_a_beat(self) -> WorkerSettings:
        if self.heartbeat_ttl_s is not None and self.heartbeat_ttl_s <= self.heartbeat_s:
            raise ValueError("PRECOND_HEARTBEAT_TTL_S must be longer than PRECOND_HEARTBEAT_S")
        return self

    def tenant_slots(self, concurrency: int) -> int:
        """Slots of a queue with `concurrency` slots that one tenant may hold."""
        return min(concurrency, self.tenant_max_running or max(1, concurrency // 2))

    @property
    def heartbeat_lease_s(self) -> float:
        """Effective heartbeat lifetime (`heartbeat_ttl_s`, or three beats)."""
        return self.heartbeat_ttl_s or 3 * self.heartbeat_s


@lru_cache(maxsize=1)
def get_worker_settings() -> WorkerSettings:
    return WorkerSettings()
