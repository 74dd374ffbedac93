"""Workers SIGKILLed mid-job and SIGTERMed mid-job: no accepted job is lost, each id has one result."""

from __future__ import annotations

from pathlib import Path

import pytest
from arq.constants import in_progress_key_prefix

from precond.stack import harness, scenarios
from precond.stack.harness import scenario_stack
from precond.stack.local import infer_body, wait_until

pytestmark = pytest.mark.stack


def test_sigkilled_workers_lose_no_job(tmp_path: Path, tiny_model_dir: Path) -> None:
    with scenario_stack("crash", tmp_path, tiny_model_dir) as stack:
        figures = scenarios.worker_crashes(stack, jobs=40, kills=3, millions=3, deadline_s=150)
    assert figures["lost"] == 0 and figures["succeeded"] == 40, figures
    assert figures["distinct_ids"] == 40 and figures["duplicates_seen"] == 0, figures
    assert figures["distinct_results"] == 1, figures  # every run of the rules gives the same answer
    # How many kills land, and whether they land mid-job, depends on the machine's speed and load; what must
    # hold whatever they hit: each kill costs at most the one model job its worker ran (concurrency 1), which
    # may be a job already re-run after an earlier kill. More runs would mean a live worker's job was taken.
    assert 40 <= figures["executions_started"] <= 40 + figures["kills"], figures
    assert figures["sandbox_servers_orphaned"] == 0, figures
    # With the default 900 s job timeout, a killed worker's jobs are handed back when its heartbeat expires
    # (1.5 s here), not 910 s later when arq's in-progress key does; the bound leaves room for a busy machine.
    if figures["kill_to_done"]["n"]:
        assert figures["kill_to_done"]["max_ms"] < 120_000, figures


def test_sigterm_mid_job_finishes_it_within_the_drain(tmp_path: Path, tiny_model_dir: Path) -> None:
    with scenario_stack("shutdown-drain", tmp_path, tiny_model_dir) as stack:
        figures = scenarios.graceful_shutdown(stack, millions=30, drain_covers_job=True)
    assert figures["worker_exit_code"] == 0, figures
    assert figures["state_when_worker_exited"] == "succeeded" and figures["runs"] == 1, figures


def test_sigterm_past_the_drain_hands_the_job_back(tmp_path: Path, tiny_model_dir: Path) -> None:
    with scenario_stack("shutdown-handback", tmp_path, tiny_model_dir) as stack:
        figures = scenarios.graceful_shutdown(stack, millions=90, drain_covers_job=False)
    assert figures["worker_exit_code"] == 0, figures
    assert figures["state_when_worker_exited"] == "queued", figures  # back in the queue, not stuck "running"
    assert figures["final_state"] == "succeeded" and figures["runs"] == 2, figures
    # Re-run at once by the next worker, not after the in-progress key's expiry (job timeout + 10 s).
    assert figures["done_after_sigterm_s"] < figures["job_timeout_s"], figures


def test_a_job_started_but_never_claimed_is_handed_back(tmp_path: Path, tiny_model_dir: Path) -> None:
    """A worker SIGKILLed after arq marked a job in progress and before it claimed the job (`on_job_start`)
    left the job to arq's in-progress expiry (job timeout + 10 s): lost for the caller. The heartbeats see a
    started job that no claim names and hand it back a lease later."""
    with scenario_stack("crash", tmp_path, tiny_model_dir) as stack, stack.http() as http:
        accepted = http.post("/infer-preconditions", json=infer_body(seed=50_000), params={"wait": 0})
        assert accepted.status_code == 202, accepted.text
        job_id = accepted.headers["X-Job-Id"]
        # what the dead worker left: arq's in-progress mark (900 s), and no claim in precond:running
        stack.redis.client().set(in_progress_key_prefix + job_id, b"1", px=900_000)
        stack.start_worker()
        wait_until(lambda: http.get(f"/jobs/{job_id}").json()["status"] == "succeeded", 60, "the job to be re-run")
        assert harness.arq_job_tries(stack.redis.client(), [job_id])[job_id] == 1
