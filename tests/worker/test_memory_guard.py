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


def test_a_training_may_grow_by_its_allowance_and_no_further() -> None:
    """A policy training loads its own copy of the model: it runs with an allowance on top of the bound, and
    is still stopped past both."""
    guard = MemoryGuard(50 * 1024 * 1024)
    guard.start()

    def grow(mib: int, allowance: int) -> str | ResourceLimit:
        try:
            with guard.running("training", allowance * 1024 * 1024):
                hoard = bytearray(mib * 1024 * 1024)
                hoard[::4096] = b"x" * len(hoard[::4096])  # touch every page: resident, not just reserved
                time.sleep(0.5)  # ten samples of the guard
                del hoard
            return "finished"
        except ResourceLimit as exc:
            return exc

    try:
        assert grow(150, allowance=300) == "finished"
        assert isinstance(grow(600, allowance=300), ResourceLimit)
    finally:
        guard.stop()
