"""What anything with write access to the queue Redis can plant is data, never code: a pickle (or any record that
fails its schema) put in place of a queued job or of a stored end, by a raw Redis client, on a real stack (its
gateway and worker processes): the worker runs nothing of it and ends the job failed with the reason, the gateway
reads nothing of it as code and answers the job as failed, and both go on serving."""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import httpx

from precond.gateway.auth import OPEN_TENANT
from precond.jobs.queue import keys
from precond.jobs.queue.keys import CHECK_QUEUE, JOB_PREFIX, RESULT_PREFIX, wake_channel
from precond.stack.local import Stack, check_body, wait_until


class Planted:
    """Unpickled, it creates `path` (what any code could do: a pickle names a callable and its arguments)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.path), "w"))


def own_job_id(stack: Stack, n: int) -> str:
    """A check job id of the open tenant, as the gateway makes them (so the gateway reads its state back)."""
    secret = stack.env["PRECOND_SECRET"].encode()
    return keys.job_id("check", {"planted": n}, None, secret, keys.tenant_tag(secret, OPEN_TENANT))


def ended(client: httpx.Client, job: str) -> dict[str, Any]:
    wait_until(lambda: client.get(f"/jobs/{job}").json()["status"] == "failed", 60, f"the end of {job}")
    return dict(client.get(f"/jobs/{job}").json())


def test_a_pickle_queued_as_a_job_runs_nothing_and_ends_failed(stack: Stack, client: httpx.Client,
                                                               tmp_path: Path) -> None:
    tmp_path.chmod(0o777)  # the worker may run as another user: the canary must be creatable by it
    canary = tmp_path / "worker-ran-the-pickle"
    job = own_job_id(stack, 1)
    redis = stack.redis.client()
    redis.set(JOB_PREFIX + job, pickle.dumps(Planted(canary)), px=600_000)
    redis.zadd(CHECK_QUEUE, {job: 1})
    redis.publish(wake_channel(CHECK_QUEUE), b"1")
    status = ended(client, job)
    assert not canary.exists(), "the worker unpickled a record from Redis"
    assert status["error"]["type"] == "internal" and "record" in status["error"]["message"], status
    served = client.post("/check-actions", json=check_body("system.REQUEST('city')"), params={"wait": 30})
    assert served.status_code == 200, served.text  # the worker lives on


def test_a_pickle_stored_as_a_jobs_end_runs_nothing_in_the_gateway(stack: Stack, client: httpx.Client,
                                                                   tmp_path: Path) -> None:
    canary = tmp_path / "gateway-ran-the-pickle"
    job = own_job_id(stack, 2)
    stack.redis.client().set(RESULT_PREFIX + job, pickle.dumps(Planted(canary)), px=600_000)
    answer = client.get(f"/jobs/{job}")
    assert not canary.exists(), "the gateway unpickled a record from Redis"
    assert answer.status_code == 200, answer.text
    status = answer.json()
    assert status["status"] == "failed" and "record" in status["error"]["message"], status
