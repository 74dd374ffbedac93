"""An idle worker is woken by the gateway's notice of a new job, not by its own poll (docs/service.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack.local import check_body, infer_body, make_stack, serving

pytestmark = pytest.mark.stack

HOUR = "3600"


def test_a_new_job_wakes_the_idle_worker_of_its_queue(tmp_path: Path, tiny_model_dir: Path) -> None:
    """The worker reads its queues on its own only once an hour here, yet every job runs at once: the first
    (enqueued right after the worker started), those after a job ended, and a model-free inference on the
    other queue. Without the notice each request waits out its `wait` and answers 202."""
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_CHECK_POLL_S=HOUR, PRECOND_WORKER_POLL_S=HOUR)
    with serving(stack, workers=1), stack.http(timeout=60) as client:
        for i in range(3):
            answer = client.post("/check-actions", json=check_body(f"system.REQUEST('slot_{i}')"),
                                 params={"wait": 30})
            assert answer.status_code == 200, answer.text
            assert answer.json()["results"][0]["allowed"] is True
        answer = client.post("/infer-preconditions", json=infer_body(seed=7), params={"wait": 30})
        assert answer.status_code == 200, answer.text
        assert answer.json()["preconditions"]
