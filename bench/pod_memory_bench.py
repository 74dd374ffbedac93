"""What a gateway pod and a worker pod hold in memory, and which paths their processes write: the figures behind
the requests, limits and writable volumes of deploy/kubernetes/ (docs/deploy.md).

    python bench/pod_memory_bench.py                          # the embedded model, converted into a fresh cache
    python bench/pod_memory_bench.py --model-cache ~/.cache/precond   # reuse converted weights (no conversion)
    python bench/pod_memory_bench.py --strace                 # also list every path opened for writing

One queue Redis, one gateway process (uvicorn, the manifests' options) and one `precond worker` with the real
sandbox and model, on loopback. Memory is read per process tree (the worker with its sandbox fork servers and
their children) as RSS and as PSS: a container's memory cgroup charges a page shared by the fork servers once,
as PSS does, while RSS counts it in every process. Sampled every 0.1 s:

  * gateway: idle, and its peak while 8 clients send uncached check-actions and cache hits for `--seconds`;
  * worker: idle with the model loaded, and its peak during one model inference (examples/infer-model.json)
    and during model-free (enumerate-only) inferences.

With `--strace` both processes run under `strace -f` (file-creating system calls only) and the bench prints
the directories they created or opened files for writing in: the paths a read-only root filesystem must leave
writable.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.gateway.server import gateway_args  # noqa: E402
from precond.stack.harness import children, rss_kib  # noqa: E402
from precond.stack.local import Stack, check_body, example, infer_body, make_stack, wait_until  # noqa: E402

WRITE_CALLS = "open,openat,openat2,creat,mkdir,mkdirat,rename,renameat,renameat2,link,linkat,symlink,symlinkat"
WRITING = re.compile(r'(?:open(?:at2?)?|creat)\((?:[A-Z_]+, )?"([^"]+)", [^)]*(?:O_WRONLY|O_RDWR|O_CREAT)')
CREATING = re.compile(r'(?:mkdir(?:at)?|rename(?:at2?)?|link(?:at)?|symlink(?:at)?)\((?:[A-Z_]+, )?"([^"]+)"')


def pss_kib(pid: int) -> int:
    """Proportional set size of one process, in KiB (0 when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def tree(pid: int) -> list[int]:
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        todo += children(current)
    return found


def tree_memory_mib(pid: int) -> dict[str, float]:
    pids = tree(pid)
    return {"rss_mib": round(sum(map(rss_kib, pids)) / 1024, 1), "pss_mib": round(sum(map(pss_kib, pids)) / 1024, 1),
            "processes": len(pids)}


class Peak:
    """The largest tree PSS (and the RSS sampled with it) of a process while a block runs."""

    def __init__(self, pid: int) -> None:
        self.pid, self.best = pid, tree_memory_mib(pid)

    async def sample(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            now = tree_memory_mib(self.pid)
            if now["pss_mib"] > self.best["pss_mib"]:
                self.best = now
            await asyncio.sleep(0.1)


async def peak_during(pid: int, work: Callable[[], Any]) -> dict[str, float]:
    peak, stop = Peak(pid), asyncio.Event()
    sampler = asyncio.create_task(peak.sample(stop))
    await work()
    stop.set()
    await sampler
    return peak.best


async def follow(http: httpx.AsyncClient, path: str, body: dict[str, Any], timeout_s: float) -> str:
    answer = await http.post(path, json=body, params={"wait": 0})
    job = answer.headers.get("X-Job-Id")
    if answer.status_code == 200 or job is None:
        return f"http {answer.status_code}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = (await http.get(f"/jobs/{job}")).json().get("status")
        if status in ("succeeded", "failed", "cancelled"):
            return str(status)
        await asyncio.sleep(0.2)
    return "timed out"


async def gateway_load(base_url: str, seconds: float) -> None:
    """Eight clients: uncached check-actions (a new call each time) and repeated cache hits."""
    calls = check_body()["calls"]
    deadline = time.monotonic() + seconds

    async def client(number: int) -> None:
        async with httpx.AsyncClient(base_url=base_url, timeout=30) as http:
            sent = 0
            while time.monotonic() < deadline:
                body = check_body(*calls) if number % 2 else check_body(*calls, f"SYSTEM.INFORM(n={number}_{sent})")
                await http.post("/check-actions", json=body)
                sent += 1

    await asyncio.gather(*(client(n) for n in range(8)))


def spawn(stack: Stack, name: str, argv: list[str], strace_dir: Path | None) -> subprocess.Popen[bytes]:
    if strace_dir is not None:
        argv = ["strace", "-f", "-qq", "-e", f"trace={WRITE_CALLS}", "-o", str(strace_dir / f"{name}.txt"), *argv]
    log = (stack.logs / f"{name}.log").open("wb")
    process = subprocess.Popen(argv, env=stack.env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    stack.processes.append(process)
    return process


def written_directories(trace: Path) -> dict[str, list[str]]:
    """Directory → the first few paths opened for writing or created in it (successfully)."""
    found: dict[str, list[str]] = {}
    for line in trace.read_text(errors="replace").splitlines():
        if "= -1" in line:
            continue
        match = WRITING.search(line) or CREATING.search(line)
        if match and not match.group(1).startswith(("/proc/", "/dev/null")):
            paths = found.setdefault(str(Path(match.group(1)).parent), [])
            if len(paths) < 3:
                paths.append(match.group(1))
    return found


async def model_loaded(stack: Stack) -> None:
    await asyncio.to_thread(wait_until, lambda: any(b.get("model_loaded") for b in stack.heartbeats()), 1800,
                            "the model to load")


def model_pid(process: subprocess.Popen[bytes], strace: bool) -> int:
    """The worker's Python process (strace's child when it runs under strace)."""
    return children(process.pid)[0] if strace else process.pid


async def measure(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    cache = Path(args.model_cache).expanduser() if args.model_cache else tmp / "models"
    stack = make_stack(tmp, Path(args.model), MODEL_PATH=args.model, MODEL_CACHE_DIR=str(cache),
                       HOME=str(tmp / "home"), TMPDIR=str(tmp / "tmp"), PRECOND_HEARTBEAT_S="2",
                       PRECOND_WORKER_POLL_S="0.1")
    (tmp / "home").mkdir()
    (tmp / "tmp").mkdir()
    strace_dir = tmp / "strace" if args.strace else None
    if strace_dir is not None:
        strace_dir.mkdir()
    figures: dict[str, Any] = {}
    try:
        gateway = spawn(stack, "gateway", [sys.executable, "-m", "uvicorn", *gateway_args(1), "--port",
                                           str(stack.port), "--log-level", "warning"], strace_dir)
        wait_until(lambda: httpx.get(f"{stack.base_url}/health").status_code == 200, 60, "gateway")
        started = time.monotonic()
        worker = spawn(stack, "worker", [sys.executable, "-m", "precond.worker.runner"], strace_dir)
        await asyncio.sleep(1)
        gateway_pid, worker_pid = model_pid(gateway, args.strace), model_pid(worker, args.strace)
        figures["worker_start"] = await peak_during(worker_pid, lambda: model_loaded(stack))
        figures["worker_ready_s"] = round(time.monotonic() - started, 1)
        await asyncio.sleep(3)
        figures["gateway_idle"] = tree_memory_mib(gateway_pid)
        figures["worker_idle"] = tree_memory_mib(worker_pid)
        async with httpx.AsyncClient(base_url=stack.base_url, timeout=60) as http:
            body = example("infer-model")
            states: list[Any] = []

            async def model_job() -> None:
                states.append(await follow(http, "/infer-preconditions", body, 1800))

            async def model_free_jobs() -> None:
                states.extend(await asyncio.gather(*(follow(http, "/infer-preconditions", infer_body(seed), 600)
                                                     for seed in range(4))))

            figures["worker_model_job"] = await peak_during(worker_pid, model_job)
            figures["worker_model_free_jobs"] = await peak_during(worker_pid, model_free_jobs)
            figures["job_states"] = states
        figures["gateway_load"] = await peak_during(gateway_pid, lambda: gateway_load(stack.base_url, args.seconds))
        figures["worker_after"] = tree_memory_mib(worker_pid)
        figures["model_cache_mib"] = round(sum(f.stat().st_size for f in cache.rglob("*") if f.is_file()) / 2**20)
    finally:
        stack.stop()
        stack.redis.stop()
    if strace_dir is not None:
        figures["written"] = {name: written_directories(strace_dir / f"{name}.txt") for name in ("gateway", "worker")}
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="embedded", help="MODEL_PATH of the worker [embedded].")
    parser.add_argument("--model-cache", help="MODEL_CACHE_DIR (default: a fresh directory: converts the model).")
    parser.add_argument("--seconds", type=float, default=10.0, help="Length of the gateway's load.")
    parser.add_argument("--strace", action="store_true", help="List the paths each process writes.")
    parser.add_argument("--json", help="Also write the figures to this file.")
    args = parser.parse_args()
    if args.strace and shutil.which("strace") is None:
        parser.error("--strace needs the strace command (Debian package strace)")
    tmp = Path(tempfile.mkdtemp(prefix="pod-memory-"))
    try:
        figures = asyncio.run(measure(args, tmp))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(figures, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
