"""A job that grows the worker's own memory past its bound fails alone; the worker and its other jobs go on
(a poison job can take a worker past 1 GB in about a second, then the next worker the same way)."""

from __future__ import annotations

import threading
import time

import pytest

from precond.worker.memory import MemoryGuard
from precond_client.schemas.errors import ResourceLimit


def test_the_job_that_grows_the_worker_is_stopped_and_the_others_go_on() -> None:
    guard = MemoryGuard(150 * 1024 * 1024)
    guard.start()
    outcomes: dict[str, object] = {}
    quiet_started = threading.Event()

    def greedy() -> None:
        quiet_started.wait(5)
        try:
            with guard.running("greedy"):
                hoard = []
                while len(hoard) < 50_000_000:  # about 2 GiB of distinct strings if nothing stops it
                    hoard.append(f"argument list {len(hoard)}")
            outcomes["greedy"] = "finished"
        except ResourceLimit as exc:
            outcomes["greedy"] = exc

    def quiet() -> None:
        with guard.running("quiet"):
            quiet_started.set()
            deadline = time.monotonic() + 3
            while time.monotonic() < deadline and "greedy" not in outcomes:
                time.sleep(0.01)
        outcomes["quiet"] = "finished"

    threads = [threading.Thread(target=greedy), threading.Thread(target=quiet)]
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
    finally:
        guard.stop()
    assert isinstance(outcomes["greedy"], ResourceLimit), outcomes
    assert "PRECOND_JOB_MAX_MEMORY_MB" in str(outcomes["greedy"])
    assert outcomes["quiet"] == "finished"


def test_a_memory_error_of_the_jobs_own_is_not_taken_for_the_guards() -> None:
    guard = MemoryGuard(150 * 1024 * 1024)
    with pytest.raises(MemoryError), guard.running("own"):
        raise MemoryError
