"""Scale-out on one machine: throughput of uncached work with 1, 2 and 4 workers against one queue Redis (and
one cache Redis), what each process spends of the CPU, and what each job costs Redis.

    python bench/scale_bench.py                     # 1, 2, 4 workers, 20 s of checks and 60 inferences each
    python bench/scale_bench.py --workers 1 2 --seconds 10 --inferences 30 --json bench/scale.json

The stack is the deployment's, one process each, with the settings' defaults (heartbeats, polls, slots;
only the request rate and the queue bound are lifted for the load): queue Redis and cache Redis with a
password, one gateway process (uvicorn, as the manifests start it), N `precond worker` processes with the real
sandbox. Workers load the tiny random model of precond/stack/tiny_model.py: the work measured needs no model.
One tenant sends everything, allowed all of a worker's slots (PRECOND_TENANT_MAX_RUNNING=4).

For each number of workers:
  * checks: `--clients` clients send uncached check-actions (a call never sent before, so every request is a
    job) for `--seconds`; checks/s;
  * inferences: `--inferences` uncached enumerate-only inferences (`generators: ["enumerate"]`, the model-free
    queue) submitted at once and followed to their end; inferences/s from the first submission to the last end;
  * per phase: CPU seconds of the gateway, the workers (with their fork servers), each Redis and this client,
    over the phase's wall time (cores used; the machine has what `os.cpu_count()` says, shared with whatever
    else runs: `uptime` is printed); Redis commands per job from `INFO commandstats` (reset before the phase;
    it counts every command a Lua script runs, and the script call), less the idle stack's rate (heartbeats,
    polls), measured for `--idle-seconds` before;
  * Redis memory: `used_memory` per queued inference (submitted with no worker running), per finished
    inference and check (its result and progress in the queue Redis, kept PRECOND_RESULT_TTL_S) and per cached
    result (in the cache Redis, kept PRECOND_CACHE_TTL_S).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.stack.harness import children  # noqa: E402
from precond.stack.local import Stack, check_body, infer_body, make_stack, serving, wait_until  # noqa: E402
from precond.stack.tiny_model import build_tiny_model  # noqa: E402

TEST_SETTINGS = ("PRECOND_HEARTBEAT_S", "PRECOND_WORKER_POLL_S", "PRECOND_WAIT_POLL_S", "PRECOND_DRAIN_S",
                 "SANDBOX_TIMEOUT_S", "SANDBOX_CPU_S", "SANDBOX_WORKERS", "PRECOND_MAX_BODY_BYTES")
"""What precond.stack.local sets for its tests' speed: removed here, so that the defaults are measured."""
LOAD_SETTINGS = {"PRECOND_TENANT_RATE_PER_S": "100000", "PRECOND_TENANT_BURST": "100000",
                 "PRECOND_TENANT_MAX_JOBS": "100000", "PRECOND_QUEUE_MAX_JOBS": "100000",
                 "PRECOND_TENANT_MAX_RUNNING": "4", "PRECOND_CHECK_PROCESSES": "1"}
TICKS = os.sysconf("SC_CLK_TCK")
POLL_S = 0.25
"""How often a client asks for an inference it follows (each finished one answers its whole result)."""
CONNECTIONS = httpx.Limits(max_connections=16)


def cpu_s(pid: int) -> float:
    """User + system CPU of a process and its descendants, living and reaped."""
    total, todo = 0.0, [pid]
    while todo:
        current = todo.pop()
        try:
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += sum(int(f) for f in fields[11:15]) / TICKS  # utime stime cutime cstime
        todo += children(current)
    return total


def roles(stack: Stack) -> dict[str, list[int]]:
    found: dict[str, list[int]] = {"gateway": [], "workers": [], "queue redis": [], "cache redis": []}
    for process in stack.processes:
        if process.poll() is None:
            found["gateway" if "uvicorn" in process.args else "workers"].append(process.pid)  # type: ignore[operator]
    for name, server in (("queue redis", stack.redis), ("cache redis", stack.cache_redis)):
        if server is not None and server.process is not None:
            found[name].append(server.process.pid)
    found["this client"] = [os.getpid()]
    return found


@contextmanager
def measured(stack: Stack, figures: dict[str, Any]) -> Iterator[None]:
    """CPU per role (cores over the block's wall time) and Redis commands, into `figures`."""
    servers = [s.client() for s in (stack.redis, stack.cache_redis) if s is not None]
    for client in servers:
        client.config_resetstat()
    who = roles(stack)
    before = {role: sum(map(cpu_s, pids)) for role, pids in who.items()}
    started = time.monotonic()
    yield
    wall = time.monotonic() - started
    figures["seconds"] = round(wall, 2)
    figures["cores"] = {role: round((sum(map(cpu_s, pids)) - before[role]) / wall, 2) for role, pids in who.items()}
    commands: Counter[str] = Counter()
    for client in servers:
        for name, stats in client.info("commandstats").items():
            commands[name.removeprefix("cmdstat_")] += int(stats["calls"])
    figures["redis_commands"] = dict(commands.most_common())


async def checks(base_url: str, clients: int, seconds: float) -> int:
    done = 0
    deadline = time.monotonic() + seconds

    async def client(number: int) -> None:
        nonlocal done
        template = check_body()
        async with httpx.AsyncClient(base_url=base_url, timeout=120) as http:
            sent = 0
            while time.monotonic() < deadline:
                body = {**template, "calls": [f"system.REQUEST('c{number}_{sent}_{time.monotonic_ns()}')"]}
                answer = await http.post("/check-actions", json=body)
                if answer.status_code != 200:
                    raise RuntimeError(f"check answered {answer.status_code}: {answer.text[:300]}")
                done += 1
                sent += 1

    await asyncio.gather(*(client(n) for n in range(clients)))
    return done


async def submit(http: httpx.AsyncClient, body: dict[str, Any]) -> str:
    answer = await http.post("/infer-preconditions", json=body, params={"wait": 0})
    if answer.status_code != 202:
        raise RuntimeError(f"inference answered {answer.status_code}: {answer.text[:300]}")
    return str(answer.headers["X-Job-Id"])


async def finish(http: httpx.AsyncClient, job: str) -> None:
    while True:
        await asyncio.sleep(POLL_S)
        try:
            status = (await http.get(f"/jobs/{job}")).json()["status"]
        except httpx.TransportError:  # a busy gateway may drop a poll: the job goes on, poll again
            continue
        if status == "succeeded":
            return
        if status in ("failed", "cancelled"):
            raise RuntimeError(f"inference {job} {status}")


async def inferences(base_url: str, count: int, first_seed: int) -> None:
    async with httpx.AsyncClient(base_url=base_url, timeout=120, limits=CONNECTIONS) as http:
        jobs = await asyncio.gather(*(submit(http, infer_body(first_seed + n)) for n in range(count)))
        await asyncio.gather(*(finish(http, job) for job in jobs))


def used_memory(server: Any) -> int:
    return int(server.client().info("memory")["used_memory"])


async def job_memory(stack: Stack, count: int) -> dict[str, int]:
    """Redis bytes per queued inference (no worker running yet), per finished one and per cached result; the
    same per finished and per cached check."""
    assert stack.cache_redis is not None
    queue_before, cache_before = used_memory(stack.redis), used_memory(stack.cache_redis)
    async with httpx.AsyncClient(base_url=stack.base_url, timeout=120, limits=CONNECTIONS) as http:
        jobs = [await submit(http, infer_body(10**6 + n)) for n in range(count)]
        queued = used_memory(stack.redis)
        stack.start_worker()
        await asyncio.gather(*(finish(http, job) for job in jobs))
        await asyncio.sleep(1)
        figures = {"inference_queued_bytes": round((queued - queue_before) / count),
                   "inference_finished_bytes": round((used_memory(stack.redis) - queue_before) / count),
                   "inference_cached_bytes": round((used_memory(stack.cache_redis) - cache_before) / count)}
        queue_before, cache_before = used_memory(stack.redis), used_memory(stack.cache_redis)
        template = check_body()
        for n in range(count):
            answer = await http.post("/check-actions", json={**template, "calls": [f"system.REQUEST('m{n}')"]})
            assert answer.status_code == 200, answer.text
        await asyncio.sleep(1)
        figures |= {"check_finished_bytes": round((used_memory(stack.redis) - queue_before) / count),
                    "check_cached_bytes": round((used_memory(stack.cache_redis) - cache_before) / count)}
    return figures


async def idle_commands_per_s(stack: Stack, seconds: float) -> float:
    """Commands the queue Redis runs per second with nothing to do: heartbeats, polls, the gateway's reads."""
    client = stack.redis.client()
    client.config_resetstat()
    await asyncio.sleep(seconds)
    calls = sum(int(stats["calls"]) for stats in client.info("commandstats").values())
    return round(calls / seconds, 1)


def per_job(phase: dict[str, Any], idle_per_s: float, jobs: int) -> float:
    """Commands a job adds: those of the phase (Lua scripts count each command they run, and the script
    call itself), less what the idle stack would have run in that time."""
    commands: int = sum(phase["redis_commands"].values())
    return round((commands - idle_per_s * float(phase["seconds"])) / jobs, 1)


def start_workers(stack: Stack, count: int) -> None:
    while len(stack.worker_pids()) < count:
        stack.start_worker()
    wait_until(lambda: sum(bool(b.get("model_loaded")) for b in stack.heartbeats()) >= count, 600, "workers")


def build(tmp: Path, model_dir: Path) -> Stack:
    tmp.mkdir()
    stack = make_stack(tmp, model_dir, cache_config="--maxmemory 256mb --maxmemory-policy allkeys-lru",
                       **LOAD_SETTINGS)
    for name in TEST_SETTINGS:
        stack.env.pop(name, None)
    return stack


async def run(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    model_dir = build_tiny_model(tmp / "model")
    results: dict[str, Any] = {"cpu_count": os.cpu_count(), "load_before": os.getloadavg(), "runs": {}}
    with serving(build(tmp / "memory", model_dir)) as stack:
        results["redis_memory"] = await job_memory(stack, args.memory_jobs)
    for workers in args.workers:
        with serving(build(tmp / f"workers-{workers}", model_dir)) as stack:
            start_workers(stack, workers)
            await inferences(stack.base_url, 4, 0)  # warm every worker's fork servers
            idle = await idle_commands_per_s(stack, args.idle_seconds)
            check_figures: dict[str, Any] = {}
            with measured(stack, check_figures):
                started = time.monotonic()
                count = await checks(stack.base_url, args.clients, args.seconds)
                check_figures["per_s"] = round(count / (time.monotonic() - started), 1)
            check_figures["redis_commands_per_job"] = per_job(check_figures, idle, count)
            check_figures["jobs"] = count
            infer_figures: dict[str, Any] = {}
            with measured(stack, infer_figures):
                started = time.monotonic()
                await inferences(stack.base_url, args.inferences, 1000)
                infer_figures["per_s"] = round(args.inferences / (time.monotonic() - started), 2)
            infer_figures["redis_commands_per_job"] = per_job(infer_figures, idle, args.inferences)
            figures: dict[str, Any] = {"checks": check_figures, "inferences": infer_figures,
                                       "idle_redis_commands_per_s": idle, "load": os.getloadavg()}
        results["runs"][workers] = figures
        print(f"{workers} workers: {figures['checks']['per_s']} checks/s, {figures['inferences']['per_s']} "
              f"inferences/s, cores {figures['checks']['cores']}", file=sys.stderr)
    return results


def table(results: dict[str, Any]) -> str:
    def cores(phase: dict[str, Any]) -> str:
        used = phase["cores"]
        return (f"{used['gateway']} / {used['workers']} / {used['queue redis'] + used['cache redis']:.2f} / "
                f"{used['this client']}")

    lines = ["| workers | checks/s | inferences/s | cores, checks: gateway / workers / Redis / client "
             "| cores, inferences: the same | Redis commands per check / per inference |",
             "| --- | --- | --- | --- | --- | --- |"]
    for workers, figures in results["runs"].items():
        checks, infers = figures["checks"], figures["inferences"]
        lines.append(f"| {workers} | {checks['per_s']} | {infers['per_s']} | {cores(checks)} | {cores(infers)} | "
                     f"{checks['redis_commands_per_job']} / {infers['redis_commands_per_job']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--clients", type=int, default=16, help="Concurrent check clients.")
    parser.add_argument("--seconds", type=float, default=20.0, help="Length of each check phase.")
    parser.add_argument("--inferences", type=int, default=60, help="Inferences per phase.")
    parser.add_argument("--memory-jobs", type=int, default=50, help="Jobs of each kind for the memory figures.")
    parser.add_argument("--idle-seconds", type=float, default=10.0, help="Idle phase for the background rate.")
    parser.add_argument("--json", help="Also write the figures to this file.")
    args = parser.parse_args()
    if shutil.which("redis-server") is None:
        parser.error("needs redis-server")
    tmp = Path(tempfile.mkdtemp(prefix="scale-bench-"))
    try:
        results = asyncio.run(run(args, tmp))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    results["uptime"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(json.dumps(results, indent=2))
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
