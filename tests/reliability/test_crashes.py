"""Workers SIGKILLed mid-job and SIGTERMed mid-job: no accepted job is lost, each id has one result."""

from __future__ import annotations

from pathlib import Path

from stack import scenarios
from stack.harness import scenario_stack


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
