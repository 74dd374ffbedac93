"""The gateway's settings (`PRECOND_*`), read once per process."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field

from precond.jobs.settings import QueueSettings
from precond_client.schemas import MAX_COUNTEREXAMPLE_RUNS


class GatewaySettings(QueueSettings):
    """The REST gateway (`precond/gateway/`), and `precond serve`, which runs it."""

    port: int = Field(
        default=8000,
        ge=1,
        le=65535,
        validation_alias=AliasChoices("PORT", "PRECOND_PORT"),
        description="Port `precond serve` (and so scripts/serve.sh) binds the gateway to; `--port` overrides it.",
    )
    processes: int = Field(
        default=1, ge=1, le=64,
        validation_alias=AliasChoices("PRECOND_GATEWAY_PROCESSES", "WEB_CONCURRENCY"),
        description="Gateway processes behind one port (uvicorn `--workers`): one event loop uses one core, so "
        "a cache-hit-heavy deployment sets this to its cores (bench/service_bench.py: 1,082 -> 2,112 cache hits "
        "a second on 2 cores). Per-process bounds (the open routes' buckets, the check processes) apply to each.",
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
    api_keys_file: Path | None = Field(
        default=None,
        description="The API keys (JSON lines, hashed; `precond keys create|list|revoke`): every request but "
        "/health, /ready and /metrics needs `Authorization: Bearer <key>`, and each key names its tenant. "
        "Re-read when it changes. Unset: the API is open, every caller is the tenant `public`.",
    )
    require_auth: bool = Field(
        default=False,
        description="Refuse to start without a keys file holding at least one key (docker-compose sets it).",
    )
    recent_results_bytes: int = Field(
        default=16 * 1024 * 1024, ge=0,
        description="Memory per gateway process for the cached results it read last (each up to 64 KiB, kept a "
        "minute at most): a repeated request is answered without a round trip to the cache Redis. 0: none.",
    )
    share_cache: bool = Field(
        default=False,
        description="Let tenants share cached results of identical requests (each tenant's own by default).",
    )
    interpret_checks: bool = Field(
        default=True,
        description="Judge a check in the gateway itself when its spec is one a converter writes and every rule "
        "is one the restricted interpreter evaluates (`judged_by: interpreter`: no job, no sandbox, nothing of the "
        "request run); false: every check is a job the sandbox judges.",
    )
    tenant_rate_per_s: float = Field(
        default=50.0, gt=0,
        description="Requests per second one tenant may send, on every route that needs a key (a token bucket, "
        "429 above).",
    )
    tenant_burst: int = Field(default=100, ge=1, description="Requests one tenant may send at once.")
    public_rate_limit: bool = Field(
        default=True,
        description="Without API keys: whether the one tenant every caller then is (`public`) is held to "
        "PRECOND_TENANT_RATE_PER_S and PRECOND_TENANT_BURST. `precond serve --no-rate-limit` turns it off for "
        "local use (a loopback address); keyed tenants are always held to their rate.",
    )
    auth_failures_per_s: float = Field(
        default=1.0, gt=0,
        description="Failed authentications (missing, unknown, revoked or expired key) one source address may "
        "make per second (a token bucket shared by all gateways); past it every request of that address is "
        "429 `auth_limited` until a token is back, before its key is looked at.",
    )
    open_rate_per_s: float = Field(
        default=50.0, gt=0,
        description="Requests per second one source address may send to the routes open without a key "
        "(/health, /ready, /metrics; a token bucket per gateway process, 429 above).",
    )
    open_burst: int = Field(default=100, ge=1, description="Requests one source address may send to them at once.")
    auth_failure_burst: int = Field(
        default=20, ge=1, description="Failed authentications one source address may make at once."
    )
    tenant_max_jobs: int = Field(
        default=32, ge=1, description="Jobs one tenant may have queued or running at once (429 above)."
    )
    max_sets_per_tenant: int = Field(
        default=100, ge=0,
        description="Precondition sets one tenant may store (422 above). Sets live in the queue Redis without "
        "expiry; PRECOND_MAX_SET_BYTES_PER_TENANT bounds the bytes of all of them.",
    )
    max_set_versions: int = Field(
        default=50, ge=1, description="Versions one precondition set may have (422 above: create a new set)."
    )
    max_set_counterexamples: int = Field(
        default=100, ge=1, le=MAX_COUNTEREXAMPLE_RUNS,
        description="Labelled calls one precondition set may keep (POST /precondition-sets/{id}/counterexamples; "
        "422 `sets_limited` above): every re-inference of the set judges each of them in the sandbox.",
    )
    max_set_bytes: int = Field(
        default=1_000_000, ge=1_000,
        description="Size of one stored version (spec, rules, demonstrations as JSON) in bytes (413 above).",
    )
    max_set_bytes_per_tenant: int = Field(
        default=32_000_000, ge=1_000,
        description="Bytes all of one tenant's stored precondition sets may take, every version counted (422 "
        "`sets_limited` above). Sets never expire and live in the queue Redis, whose memory every tenant's jobs "
        "need: size it for this times the number of tenants (keys file) plus the queue's own needs.",
    )
    max_policies_per_tenant: int = Field(
        default=4, ge=0,
        description="Trained policies (POST /policies) one tenant may store (422 above: delete one first).",
    )
    max_policy_versions: int = Field(default=5, ge=1, description="Versions one trained policy may have (422 above).")
    max_policy_bytes_per_tenant: int = Field(
        default=48_000_000, ge=1_000_000,
        description="Bytes all of one tenant's trained policies may take, every version counted (422 above). A "
        "rank-8 adapter of the embedded model is 4.4 MB. Like precondition sets they never expire and live in the "
        "queue Redis: size it for this times the number of tenants as well.",
    )
    max_training_steps: int = Field(
        default=48, ge=1, le=400,
        description="Most `options.steps` of one policy training (422 above, naming the field): a step is about "
        "9 s of a worker's training slot on 2 CPU cores for the embedded model, and a training must end within "
        "PRECOND_JOB_TIMEOUT_S.",
    )
    check_processes: int = Field(default=2, ge=1, description=(
        "Processes per gateway that parse and check large requests' programs (spec, demonstrations, history) off "
        "the event loop: parsing holds Python's GIL, so a thread would stall every other client."))
    tenant_check_processes: int = Field(default=1, ge=1, description=(
        "Of those, how many one tenant's requests may use at once (the rest wait in its own line)."))
    max_work_points: int = Field(
        default=2_000_000,
        ge=1,
        validation_alias=AliasChoices("PRECOND_MAX_WORK_POINTS", "SANDBOX_MAX_POINTS"),
        description="Work budget of one request: demonstration steps x distinct argument tuples of its most "
        "varied action (the points every candidate is judged at); 422 above, before anything is queued. One "
        "budget: the sandbox counts the same points exactly (`SandboxSettings.max_points`, the same variable).",
    )


@lru_cache(maxsize=1)
def get_gateway_settings() -> GatewaySettings:
    """One instance per process: the environment does not change under a running service."""
    return GatewaySettings()
