"""Failures an operator will see: a worker SIGKILLed mid-job, Redis going away and coming back."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.service.conftest import SPEC, Stack, infer_body, make_stack, wait_until


@pytest.fixture()
def own_stack(tmp_path: Path) -> Iterator[Stack]:
    # job_timeout 2 s: arq re-runs a dead worker's job once its in-progress key expires (timeout + 10 s).
    stack = make_stack(tmp_path, PRECOND_JOB_TIMEOUT_S="2", PRECOND_RETRY_AFTER_S="2")
    try:
        stack.start_gateway()
        yield stack
    finally:
        stack.stop()
        stack.redis.stop()


def test_job_of_a_killed_worker_completes_on_another(own_stack: Stack) -> None:
    doomed = own_stack.start_worker()
    with own_stack.http() as client:
        answer = client.post(
            "/infer-preconditions", json=infer_body(SPEC + "# slow: 1.5\n"), params={"wait": 0}
        )
        location = answer.headers["Location"]
        wait_until(lambda: client.get(location).json()["status"] == "running", 5, "job start")
        doomed.send_signal(signal.SIGKILL)
        doomed.wait()
        own_stack.start_worker()
        wait_until(
            lambda: client.get(location).json()["status"] == "succeeded", 25, "re-run on the second worker"
        )


def test_redis_outage_is_503_then_recovers(own_stack: Stack) -> None:
    own_stack.start_worker()
    check = {"spec": SPEC, "history": "user = USER()\n", "calls": ["system.REQUEST('a')"]}
    with own_stack.http() as client:
        assert client.post("/check-actions", json=check).status_code == 200
        own_stack.redis.stop()
        down = client.post("/check-actions", json={**check, "calls": ["system.REQUEST('b')"]})
        assert down.status_code == 503
        assert down.json()["error"]["type"] == "unavailable"
        assert down.headers["Retry-After"] == "2"
        assert client.get("/ready").status_code == 503
        assert client.get("/health").status_code == 200
        own_stack.redis.start()
        wait_until(lambda: client.get("/ready").status_code == 200, 20, "workers back on the new Redis")
        again = client.post(
            "/check-actions", json={**check, "calls": ["system.REQUEST('c')"]}, params={"wait": 10}
        )
        assert again.status_code == 200, again.text
