"""Failures an operator will see: a worker SIGKILLed mid-job, Redis going away and coming back."""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.service.stack import Stack, check_body, heavy_infer_body, make_stack, wait_until

JOB_TIMEOUT_S = 8
"""arq re-runs a dead worker's job once its in-progress key expires: job timeout + 10 s after it started."""


@pytest.fixture()
def own_stack(tmp_path: Path, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(
        tmp_path, tiny_model_dir, PRECOND_JOB_TIMEOUT_S=str(JOB_TIMEOUT_S), PRECOND_RETRY_AFTER_S="2"
    )
    try:
        stack.start_gateway()
        yield stack
    finally:
        stack.stop()
        stack.redis.stop()


def test_job_of_a_killed_worker_completes_on_another(own_stack: Stack) -> None:
    doomed = own_stack.start_worker()
    # A real, slow job: its first demonstration sums 30 million numbers each time the sandbox runs it (trace,
    # validate, verify), so it runs for a second or two, far below the job timeout and the sandbox's limits.
    body = heavy_infer_body(seed=1, millions=30)
    with own_stack.http() as client:
        answer = client.post("/infer-preconditions", json=body, params={"wait": 0})
        location = answer.headers["Location"]
        wait_until(lambda: client.get(location).json()["status"] == "running", 30, "job start")
        doomed.send_signal(signal.SIGKILL)
        doomed.wait()
        killed_at = time.monotonic()
        assert client.get(location).json()["status"] in ("queued", "running")  # nobody finished it
        own_stack.start_worker()
        wait_until(
            lambda: client.get(location).json()["status"] == "succeeded", 60, "re-run on the second worker"
        )
        assert time.monotonic() - killed_at < JOB_TIMEOUT_S + 10 + 30
        result = client.get(location).json()["result"]
        assert result["stats"]["total"]["valid"] > 0 and "SYSTEM.GOODBYE" in result["preconditions"]


def test_redis_outage_is_503_then_recovers(own_stack: Stack) -> None:
    own_stack.start_worker()
    with own_stack.http() as client:
        first = client.post("/check-actions", json=check_body("system.REQUEST('city')"))
        assert first.status_code == 200, first.text
        assert first.json()["results"][0]["allowed"] is True
        own_stack.redis.stop()
        down = client.post("/check-actions", json=check_body("system.REQUEST('cuisine')"))
        assert down.status_code == 503
        assert down.json()["error"]["type"] == "unavailable"
        assert down.headers["Retry-After"] == "2"
        assert down.headers["X-Request-Id"] == down.json()["request_id"]
        assert client.get("/ready").status_code == 503
        assert client.get("/health").status_code == 200
        own_stack.redis.start()
        wait_until(lambda: client.get("/ready").status_code == 200, 30, "workers back on the new Redis")
        again = client.post("/check-actions", json=check_body("system.REQUEST('time')"), params={"wait": 10})
        assert again.status_code == 200, again.text
        assert again.json()["results"][0]["call"] == "system.REQUEST('time')"
