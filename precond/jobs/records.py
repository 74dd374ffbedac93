"""What a worker writes and the gateway reads back beside a job's end: progress and stats.

* Progress: a `ProgressRecord` (the API's `JobProgress`, versioned: precond/jobs/queue/payloads.py) as JSON under
  `progress_key(job id)`.
* Stats: the workers' counters in one Redis hash (`STATS_KEY`), named by the functions here and read back
  into a `StatsSnapshot` for /metrics. A worker process adds its jobs' counts up (`PendingCounts`) and its
  heartbeat writes them, one HINCRBYFLOAT a name per beat (precond/jobs/queue/heartbeats.py), rather than a few
  commands per job in the script that ends it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from redis.asyncio import Redis

from precond.jobs.queue.keys import STATS_KEY, JobId, progress_key
from precond.jobs.queue.payloads import encode_progress
from precond_client.schemas import JobKind, JobProgress

OutcomeState = Literal["succeeded", "failed"]


# ---- progress -------------------------------------------------------------------------------------------


async def write_progress(redis: Redis[bytes], job_id: str, progress: JobProgress, ttl_s: int) -> None:
    await redis.set(progress_key(job_id), encode_progress(progress), ex=ttl_s)


# ---- stats ----------------------------------------------------------------------------------------------

SANDBOX_FAILURES = "sandbox_failures"


class PendingCounts:
    """Counts a worker process has added up and not yet written to `STATS_KEY`. They are metrics, never a job's
    state: a SIGKILLed process loses its last beat period's, and a beat whose answer was lost may count them twice
    (they are added back when a beat fails)."""

    def __init__(self) -> None:
        self._counts: dict[str, float] = {}

    def add(self, counts: Mapping[str, float]) -> None:
        for name, value in counts.items():
            self._counts[name] = self._counts.get(name, 0.0) + value

    def take(self) -> dict[str, float]:
        """The counts added so far, forgotten here (`add` them back when they could not be written)."""
        counts, self._counts = self._counts, {}
        return counts


async def write_counts(redis: Redis[bytes], counts: Mapping[str, float]) -> None:
    """Add `counts` to the workers' stats at once (a worker's last counts, as it stops)."""
    if counts:
        async with redis.pipeline(transaction=False) as pipe:
            for name, value in counts.items():
                pipe.hincrbyfloat(STATS_KEY, name, value)
            await pipe.execute()


def job_counts(kind: JobKind, status: OutcomeState, sandbox_limit: bool) -> dict[str, float]:
    """A finished job's counts, by kind and outcome (and whether a sandbox limit stopped it): added up by its
    worker once the job's end is recorded (precond/worker/queue_worker.py)."""
    counts = {f"jobs:{kind}:{status}": 1.0}
    if sandbox_limit:
        counts[SANDBOX_FAILURES] = 1.0
    return counts


def queue_time_counts(job: JobId, seconds: float) -> dict[str, float]:
    """How long a job waited before a worker started it, per tenant: fairness, as the operator sees it."""
    return {f"queue_sum:{job.tenant}:{job.kind}": max(0.0, seconds), f"queue_count:{job.tenant}:{job.kind}": 1.0}


async def record_phase(redis: Redis[bytes], kind: JobKind, phase: str, seconds: float) -> None:
    """Add one engine phase's wall time to its kind's running sum and count."""
    await redis.hincrbyfloat(STATS_KEY, f"phase_sum:{kind}:{phase}", seconds)
    await redis.hincrby(STATS_KEY, f"phase_count:{kind}:{phase}", 1)


@dataclass
class StatsSnapshot:
    jobs: dict[tuple[str, str], float] = field(default_factory=dict)  # (kind, outcome) -> count
    phase_sum: dict[tuple[str, str], float] = field(default_factory=dict)  # (kind, phase) -> seconds
    phase_count: dict[tuple[str, str], float] = field(default_factory=dict)  # (kind, phase) -> runs
    queue_sum: dict[tuple[str, str], float] = field(default_factory=dict)  # (tenant tag, kind) -> seconds
    queue_count: dict[tuple[str, str], float] = field(default_factory=dict)  # (tenant tag, kind) -> jobs
    sandbox_failures: float = 0.0


async def read_stats(redis: Redis[bytes]) -> StatsSnapshot:
    snapshot = StatsSnapshot()
    for raw_name, raw_value in (await redis.hgetall(STATS_KEY)).items():
        name, value = raw_name.decode(), float(raw_value)
        if name == SANDBOX_FAILURES:
            snapshot.sandbox_failures = value
            continue
        table, _, rest = name.partition(":")
        kind, _, label = rest.partition(":")
        target = {"jobs": snapshot.jobs, "phase_sum": snapshot.phase_sum, "phase_count": snapshot.phase_count,
                  "queue_sum": snapshot.queue_sum, "queue_count": snapshot.queue_count}
        if table in target:
            target[table][(kind, label)] = value
    return snapshot
