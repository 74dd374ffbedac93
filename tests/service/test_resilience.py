"""Failures an operator will see: a worker SIGKILLed mid-job, Redis going away and coming back."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from precond.jobs.queue.payloads import decode_end
from precond.stack.local import Stack, check_body, heavy_infer_body, make_stack, serving, wait_until

HANG_GUARD_S = 300
"""How long the test waits for the re-run before failing instead of hanging: a guard, not a timing (how soon
the job comes back is measured by bench/reliability.py's crash scenario). The job timeout is the default 900 s,
so arq's own in-progress key would hold the job for 910 s: a re-run that this test sees at all came from the
survivors' heartbeats, which hand the job back once the dead worker's heartbeat expires (3 × 0.5 s here)."""


@pytest.fixture()
def own_stack(tmp_path: Path, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_RETRY_AFTER_S="2")
    assert "PRECOND_JOB_TIMEOUT_S" not in stack.env  # the default, long timeout
    with serving(stack):
        yield stack


def test_job_of_a_killed_worker_completes_on_another(own_stack: Stack) -> None:
    workers = {own_stack.start_worker().pid: "a", own_stack.start_worker().pid: "b"}
    redis = own_stack.redis.client()
    # A real, slow job: its first demonstration sums 90 million numbers each time the sandbox runs it (trace,
    # validate, verify), so it runs for several seconds, far below the job timeout and the sandbox's limits.
    body = heavy_infer_body(seed=1, millions=90)
    with own_stack.http() as client:
        answer = client.post("/infer-preconditions", json=body, params={"wait": 0})
        location, job_id = answer.headers["Location"], answer.headers["X-Job-Id"]
        wait_until(lambda: redis.hget("precond:running", job_id), 30, "the job's claim")
        holder = redis.hget("precond:running", job_id).decode().split("|")[0]  # type: ignore[union-attr]
        doomed = int(holder.split("-")[-2])
        assert doomed in workers
        # While its worker lives, the job is left alone for several heartbeat lifetimes, and the worker's
        # heartbeat never lapses although the engine is busy (it runs in a thread; beats on the event loop).
        watched = time.monotonic()
        while time.monotonic() - watched < 2.5:
            assert redis.pttl(f"precond:worker:{holder}") > 0, "a busy worker's heartbeat lapsed"
            assert client.get(location).json()["status"] == "running"
            time.sleep(0.05)
        assert redis.get(f"arq:retry:{job_id}") == b"1"  # started once: nobody took it from a live worker
        os.kill(doomed, signal.SIGKILL)
        wait_until(
            lambda: client.get(location).json()["status"] == "succeeded",
            HANG_GUARD_S,
            "re-run on the surviving worker",
        )
        result = client.get(location).json()["result"]
        assert result["stats"]["total"]["valid"] > 0 and "SYSTEM.GOODBYE" in result["preconditions"]
        assert decode_end(redis.get(f"arq:result:{job_id}")).job_try == 2  # type: ignore[arg-type]
        assert redis.hlen("precond:running") == 0  # no claim left behind


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
