"""The worker's own memory, bounded per job: a job that makes the worker grow past its bound fails alone.

Untrusted code runs in sandbox children with their own `RLIMIT_AS`; what a request makes the *engine* build in
the worker itself (candidates, argument lists, rankings) has no kernel limit, and an RLIMIT on the worker
would fail whichever job allocates next, not the one that grew. So a watchdog thread samples the worker's
resident size every `PERIOD_S`; when it passes the resident size at the start of the oldest running job by
more than `PRECOND_JOB_MAX_MEMORY_MB`, the job whose engine thread used the most CPU since the last sample
(allocating is work; a job waiting on the sandbox uses almost none) gets a `MemoryError` raised in its thread.
Its engine unwinds (freeing what it built), the job fails with a `resource_limit` naming the bound, and the
worker and the other jobs go on: no worker dies, and no poison job is handed to a second worker.
"""

from __future__ import annotations

import ctypes
import logging
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from precond_client.schemas.errors import ResourceLimit

log = logging.getLogger("precond.worker.memory")
PERIOD_S = 0.05
_PAGE = os.sysconf("SC_PAGE_SIZE")


def resident_bytes() -> int:
    with open("/proc/self/statm", "rb") as statm:
        return int(statm.read().split()[1]) * _PAGE


def _thread_cpu_ticks(native_id: int) -> int:
    try:
        with open(f"/proc/self/task/{native_id}/stat", "rb") as stat:
            fields = stat.read().rsplit(b")", 1)[1].split()
    except OSError:
        return 0
    return int(fields[11]) + int(fields[12])  # utime, stime


@dataclass
class _Run:
    job_id: str
    ident: int
    native_id: int
    resident_at_start: int
    cpu_ticks: int
    stopped_at: int | None = None


class MemoryGuard:
    def __init__(self, max_growth_bytes: int) -> None:
        self.max_growth_bytes = max_growth_bytes
        self._runs: dict[int, _Run] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="memory-guard", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    @contextmanager
    def running(self, job_id: str) -> Iterator[None]:
        """Around a job's engine work, in the thread that does it; a stop for memory becomes ResourceLimit. (A
        policy training grows a process of its own, bounded there: precond/worker/training_process.py.)"""
        native_id = threading.get_native_id()
        run = _Run(job_id, threading.get_ident(), native_id, resident_bytes(), _thread_cpu_ticks(native_id))
        with self._lock:
            self._runs[run.ident] = run
        try:
            yield
        except MemoryError:
            if run.stopped_at is None:
                raise
            raise self._limit(run) from None
        finally:
            with self._lock:
                del self._runs[run.ident]
        if run.stopped_at is not None:  # raised too late to land in the engine: the result is still refused
            raise self._limit(run)

    def _limit(self, run: _Run) -> ResourceLimit:
        mib = 1024 * 1024
        return ResourceLimit(
            f"the job grew its worker's memory to {(run.stopped_at or 0) // mib:,} MiB, more than "
            f"{self.max_growth_bytes // mib:,} MiB over its size when the job started (PRECOND_JOB_MAX_MEMORY_MB); "
            "it was stopped: send a smaller spec or fewer demonstrations"
        )

    def _watch(self) -> None:
        while not self._stop.wait(PERIOD_S):
            try:
                self.check()
            except Exception:  # the guard must keep watching whatever one sample does
                log.exception("memory guard sample failed")

    def check(self) -> None:
        """One sample: stop the busiest running job if the worker grew past the bound."""
        resident = resident_bytes()
        with self._lock:
            runs = [run for run in self._runs.values() if run.stopped_at is None]
            if not runs:
                return
            spent = {run.ident: _thread_cpu_ticks(run.native_id) for run in runs}
            busiest = max(runs, key=lambda run: spent[run.ident] - run.cpu_ticks)
            for run in runs:
                run.cpu_ticks = spent[run.ident]
            if resident - min(run.resident_at_start for run in runs) <= self.max_growth_bytes:
                return
            busiest.stopped_at = resident
        log.error("job %s grew the worker to %d MiB: stopping it", busiest.job_id, resident // (1024 * 1024))
        ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(busiest.ident), ctypes.py_object(MemoryError))
