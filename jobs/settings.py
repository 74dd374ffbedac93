"""Deployment knobs, read once from the environment so containers are configured without code changes.

The gateway and the worker share this class: a queue bound or a timeout that the two sides read differently
would show up as jobs that time out on one side and run on the other. Model settings are not here: they are
`MODEL_*` in `engine.models`, which the gateway must not import (it pulls in torch).
"""

from __future__ import annotations

from functools import lru_cache

from pydantic import AliasChoices, Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/0"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="PRECOND_", extra="ignore", frozen=True)

    redis_url: str | None = Field(
        default=None,
        validation_alias=AliasChoices("REDIS_URL", "PRECOND_REDIS_URL"),
        description="Redis for queue, cache, progress and heartbeats. Unset: 127.0.0.1:6379, and "
        "`precond serve` starts a private redis-server if nothing answers there.",
    )
    max_body_bytes: int = Field(
        default=4 * 1024 * 1024, ge=1024, description="Largest request body (413 above)."
    )
    queue_max_jobs: int = Field(default=64, ge=1, description="Jobs waiting per queue before 429.")
    retry_after_s: int = Field(default=5, ge=1, description="Retry-After sent with 429 and 503.")
    wait_max_s: float = Field(
        default=30.0, ge=0, description="How long a POST waits for its job before 202; `?wait=` can lower it."
    )
    wait_poll_s: float = Field(
        default=0.05,
        gt=0,
        description="How often a waiting request polls its job while job-completion notices (Redis pub/sub) "
        "are unavailable; with them it is woken when its job finishes.",
    )
    cache_ttl_s: int = Field(default=7 * 24 * 3600, ge=1, description="Lifetime of a cached result.")
    result_ttl_s: int = Field(
        default=3600, ge=1, description="How long GET /jobs/{id} can see a finished job."
    )
    job_timeout_s: float = Field(
        default=900.0,
        gt=0,
        description="Longest a model job may run. (A job whose worker died is handed to another worker "
        "once the dead worker's heartbeat expires, not after this timeout.)",
    )
    check_timeout_s: float = Field(default=60.0, gt=0, description="Longest a check-actions job may run.")
    job_max_tries: int = Field(
        default=3, ge=1, description="Runs of a job before it fails (worker deaths count)."
    )
    worker_concurrency: int = Field(
        default=1, ge=1, description="Model jobs one worker process runs at once."
    )
    check_concurrency: int = Field(default=4, ge=1, description="check-actions jobs one worker runs at once.")
    worker_poll_s: float = Field(
        default=0.1, gt=0, description="How often an idle worker polls the model queue (infer, next-action)."
    )
    check_poll_s: float = Field(
        default=0.01,
        gt=0,
        description="How often an idle worker polls the check queue: a check job takes milliseconds, so "
        "this wait is most of check-actions' latency (each poll is a few cheap Redis commands).",
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

    @model_validator(mode="after")
    def _ttl_outlives_a_beat(self) -> Settings:
        if self.heartbeat_ttl_s is not None and self.heartbeat_ttl_s <= self.heartbeat_s:
            raise ValueError("PRECOND_HEARTBEAT_TTL_S must be longer than PRECOND_HEARTBEAT_S")
        return self

    @property
    def heartbeat_lease_s(self) -> float:
        """Effective heartbeat lifetime (`heartbeat_ttl_s`, or three beats)."""
        return self.heartbeat_ttl_s or 3 * self.heartbeat_s

    @property
    def redis_dsn(self) -> str:
        return self.redis_url or DEFAULT_REDIS_URL


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """One instance per process: the environment does not change under a running service."""
    return Settings()
