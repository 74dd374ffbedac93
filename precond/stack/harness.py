"""Shared by tests/reliability/ (short CI variants) and bench/reliability.py (full-size runs).

Everything runs for real on loopback: redis-server (append-only file on where a scenario needs
persistence, as in docker-compose), the uvicorn gateway and `worker.runner` processes with the production
engine and sandbox, started by precond/stack/local.py. Every scenario is a function that takes its size,
runs against a stack, and returns its figures as a dict; tests assert on them, the bench prints them.
"""

from __future__ import annotations

import asyncio
import os
import signal
import statistics
import subprocess
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import redis

from precond.stack.local import RedisServer, Stack, make_stack, serving, wait_until

TERMINAL = ("succeeded", "failed", "cancelled")


@dataclass
class PersistentRedis(RedisServer):
    """redis-server as docker-compose runs it: `--appendonly yes` (fsync every second), data kept in
    `directory`, so a restart on the same directory replays the append-only file."""

    def start(self) -> None:
        self.process = subprocess.Popen(self.argv(["--appendonly", "yes", "--save", ""]), stdout=subprocess.DEVNULL)
        wait_until(lambda: self.client().ping(), 10, "redis-server")

    def kill(self) -> None:
        if self.process:
            self.process.kill()
            self.process.wait(10)


def build_stack(tmp: Path, model_dir: Path, persistent: bool = False, **settings: str) -> Stack:
    stack = make_stack(tmp, model_dir, **settings)
    if persistent:
        stack.redis.stop()
        server = PersistentRedis(tmp / "redis", port=stack.redis.port, password=stack.redis.password,
                                 config=stack.redis.config)
        server.directory.mkdir(exist_ok=True)
        server.start()
        stack.redis = server
    return stack


def gateway_pid(stack: Stack) -> int:
    return next(p.pid for p in stack.processes if "uvicorn" in p.args and p.poll() is None)  # type: ignore[operator]


def rss_kib(pid: int) -> int:
    """VmRSS of one process, in KiB (0 when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def children(pid: int) -> list[int]:
    found: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            found += [int(c) for c in (task / "children").read_text().split()]
    except OSError:
        pass
    return found


def tree_rss_kib(pid: int) -> int:
    """RSS of a process and all its descendants (a worker and its sandbox fork servers)."""
    total, todo = 0, [pid]
    while todo:
        current = todo.pop()
        total += rss_kib(current)
        todo += children(current)
    return total


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))]


def summary_ms(values: list[float]) -> dict[str, float]:
    """p50/p99/max of latencies given in seconds, in milliseconds."""
    if not values:
        return {"n": 0}
    return {"n": len(values), "p50_ms": round(percentile(values, 50) * 1000, 1),
            "p99_ms": round(percentile(values, 99) * 1000, 1), "max_ms": round(max(values) * 1000, 1)}


def arq_job_tries(client: redis.Redis[bytes], job_ids: list[str]) -> dict[str, int]:
    """The queue's own count of how often each finished job was started (its stored end's `job_try`)."""
    from precond.jobs.queue.payloads import decode_end

    tries: dict[str, int] = {}
    for job_id in job_ids:
        raw = client.get(f"arq:result:{job_id}")
        if raw is not None:
            tries[job_id] = decode_end(raw).job_try
    return tries


def claims_of(client: redis.Redis[bytes], pid: int) -> list[str]:
    """Ids of the jobs a worker process holds in `precond:running` (claims are `<host>-<pid>-<x>|<nonce>`)."""
    return [job.decode() for job, claim in client.hgetall("precond:running").items()
            if int(claim.decode().split("|")[0].split("-")[-2]) == pid]


def stats(client: redis.Redis[bytes]) -> dict[str, float]:
    return {k.decode(): float(v) for k, v in client.hgetall("precond:stats").items()}


# ---- clients -------------------------------------------------------------------------------------------


async def submit_and_follow(
    http: httpx.AsyncClient, path: str, body: dict[str, Any], deadline: float, poll_s: float = 0.25
) -> dict[str, Any]:
    """What a careful client does: POST (wait=0), then poll the job until it ends or `deadline` passes.

    Transient 429/503 answers are retried after their Retry-After (capped at 1 s here); every terminal
    state the client sees for the id is recorded, so a job that ends twice differently would show.
    """
    started = time.monotonic()
    seen: list[str] = []
    job_id = None
    while time.monotonic() < deadline:
        try:
            if job_id is None:
                answer = await http.post(path, json=body, params={"wait": 0})
                if answer.status_code in (429, 503):
                    await asyncio.sleep(min(1.0, float(answer.headers.get("Retry-After", 1))))
                    continue
                job_id = answer.headers.get("X-Job-Id")
                if answer.status_code == 200:
                    return {"id": job_id, "state": "succeeded", "latency": time.monotonic() - started,
                            "result": answer.json(), "seen": ["succeeded"]}
                if answer.status_code != 202:
                    return {"id": job_id, "state": f"http {answer.status_code}", "latency":
                            time.monotonic() - started, "result": answer.json(), "seen": seen}
            else:
                answer = await _get_within_rate(http, f"/jobs/{job_id}")
                if answer.status_code == 200 and answer.json()["status"] in TERMINAL:
                    state, ended = answer.json()["status"], time.monotonic()
                    seen.append(state)
                    # Read it once more: the state a client sees for a finished id must not change.
                    again = (await _get_within_rate(http, f"/jobs/{job_id}")).json()
                    seen.append(again.get("status", "gone"))
                    return {"id": job_id, "state": state, "latency": ended - started, "ended": ended,
                            "result": answer.json().get("result"), "seen": seen}
                if answer.status_code == 404:
                    return {"id": job_id, "state": "lost (404)", "latency": time.monotonic() - started,
                            "result": None, "seen": seen}
        except httpx.HTTPError:
            pass
        await asyncio.sleep(poll_s)
    return {"id": job_id, "state": "timed out", "latency": time.monotonic() - started, "result": None,
            "seen": seen}


async def _get_within_rate(http: httpx.AsyncClient, path: str) -> httpx.Response:
    """GET, waiting out the tenant's request rate (polls count against it, as every request does)."""
    while True:
        answer = await http.get(path)
        if answer.status_code != 429:
            return answer
        await asyncio.sleep(min(1.0, float(answer.headers.get("Retry-After", 1))))


async def bounded_gather(limit: int, factories: list[Callable[[], Awaitable[Any]]]) -> list[Any]:
    semaphore = asyncio.Semaphore(limit)

    async def one(factory: Callable[[], Awaitable[Any]]) -> Any:
        async with semaphore:
            return await factory()

    return await asyncio.gather(*(one(f) for f in factories))


def median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def sigkill(pid: int) -> None:
    os.kill(pid, signal.SIGKILL)


# ---- stacks per scenario ------------------------------------------------------------------------------

SETTINGS: dict[str, dict[str, str]] = {
    # The default job timeout (900 s): a killed worker's job is handed back once the worker's heartbeat
    # expires, not when arq's in-progress key does. The queue bound must hold every job at once.
    "crash": {"PRECOND_QUEUE_MAX_JOBS": "1000"},
    "redis": {"PRECOND_QUEUE_MAX_JOBS": "1000", "PRECOND_RETRY_AFTER_S": "2"},
    # Production body bound (4 MiB), sandbox limits as configured by SANDBOX_* (CI shortens them).
    "hostile": {"PRECOND_MAX_BODY_BYTES": "4194304", "PRECOND_WAIT_MAX_S": "60"},
    "fuzz": {"PRECOND_MAX_BODY_BYTES": "4194304", "PRECOND_WAIT_MAX_S": "2", "PRECOND_QUEUE_MAX_JOBS": "16"},
    # One tenant (the open API's) floods and probes: tenant limits set out of the way, so what is measured is
    # the queue's bound (per-tenant limits: tests/service/test_tenants.py, bench/service_bench.py).
    "overload": {"PRECOND_QUEUE_MAX_JOBS": "8", "PRECOND_JOB_TIMEOUT_S": "60", "PRECOND_TENANT_RATE_PER_S": "100000",
                 "PRECOND_TENANT_BURST": "100000", "PRECOND_TENANT_MAX_JOBS": "100000"},
    "shutdown-drain": {"PRECOND_DRAIN_S": "20", "PRECOND_JOB_TIMEOUT_S": "30"},
    "shutdown-handback": {"PRECOND_DRAIN_S": "1", "PRECOND_JOB_TIMEOUT_S": "30"},
}

FAST_SANDBOX = {"SANDBOX_TIMEOUT_S": "2", "SANDBOX_CPU_S": "2"}
"""CI: looping hostile programs cost their wall-clock limit each; production's is 10 s."""


@contextmanager
def scenario_stack(name: str, tmp: Path, model_dir: Path, persistent: bool = False,
                   **overrides: str) -> Iterator[Stack]:
    with serving(build_stack(tmp, model_dir, persistent=persistent, **{**SETTINGS[name], **overrides})) as stack:
        yield stack
