"""The reliability scenarios of docs/reliability.md, each a function of its size returning its figures.

tests/reliability/test_*.py run them small (CI), `python bench/reliability.py` runs them full size.
"""

from __future__ import annotations

import asyncio
import functools
import json
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from precond.jobs.queue.keys import MODEL_FREE_QUEUE
from precond.stack import harness
from precond.stack.hostile import hostile_requests
from precond.stack.local import ROOT, Stack, check_body, heavy_infer_body, infer_body, wait_until

# ---- worker crashes ------------------------------------------------------------------------------------


def worker_crashes(stack: Stack, jobs: int, kills: int, millions: int, workers: int = 2,
                   clients: int = 32, deadline_s: float = 600) -> dict[str, Any]:
    """`jobs` distinct infer jobs submitted at once while one worker after another is SIGKILLed.

    The killer SIGKILLs a worker `kills` times, spread over the expected run time, and starts a replacement
    right away. Whether a kill hit a running job is measured, not assumed: arq records in each result how
    often the job was started (`job_try`), so re-runs = sum(job_try) - jobs.
    """
    for _ in range(workers):
        stack.start_worker()
    bodies = [heavy_infer_body(seed=10_000 + i, millions=millions) for i in range(jobs)]
    killed: list[dict[str, Any]] = []
    orphans: list[int] = []
    done = threading.Event()
    # One job takes about 0.1 s per million on the CI box; two workers share two cores.
    expected_s = jobs * max(0.4, 0.1 * millions) / workers

    started = time.monotonic()
    thread = threading.Thread(target=_killer, args=(stack, kills, expected_s / (kills + 1), done, killed, orphans),
                              daemon=True)
    thread.start()
    outcomes = asyncio.run(_submit_all(stack, bodies, clients, deadline_s))
    done.set()
    thread.join()
    wall = time.monotonic() - started
    return _crash_report(stack, jobs, outcomes, killed, orphans, wall)


def _killer(stack: Stack, kills: int, gap_s: float, done: threading.Event, killed: list[dict[str, Any]],
            orphans: list[int]) -> None:
    """SIGKILL a random worker every `gap_s` (`kills` times, until `done`), noting the jobs it held and its
    sandbox servers, and start a replacement right away."""
    for _ in range(kills):
        if done.wait(gap_s):
            return
        pids = sorted(stack.worker_pids())
        if not pids:
            continue
        victim = random.Random(len(killed)).choice(pids)
        forks = harness.children(victim)
        held = harness.claims_of(stack.redis.client(), victim)
        harness.sigkill(victim)
        killed.append({"pid": victim, "at": time.monotonic(), "jobs": held})
        orphans.extend(forks)
        stack.start_worker()


async def _submit_all(stack: Stack, bodies: list[dict[str, Any]], clients: int, deadline_s: float
                      ) -> list[dict[str, Any]]:
    """Every body submitted and followed to its end, `clients` at a time."""
    async with httpx.AsyncClient(base_url=stack.base_url, timeout=30) as http:
        deadline = time.monotonic() + deadline_s
        return await harness.bounded_gather(clients, [
            functools.partial(harness.submit_and_follow, http, "/infer-preconditions", b, deadline)
            for b in bodies
        ])


def _crash_report(stack: Stack, jobs: int, outcomes: list[dict[str, Any]], killed: list[dict[str, Any]],
                  orphans: list[int], wall: float) -> dict[str, Any]:
    """What the crashes cost: jobs lost or run twice, latencies, the hand-back delay, orphaned servers."""
    client = stack.redis.client()
    ids = [o["id"] for o in outcomes if o["id"]]
    tries = harness.arq_job_tries(client, ids)
    rules = {json.dumps(o["result"]["preconditions"], sort_keys=True) for o in outcomes
             if o["state"] == "succeeded"}
    rerun = [o for o in outcomes if tries.get(o["id"], 1) > 1]
    once = [o for o in outcomes if tries.get(o["id"], 1) == 1]
    ended = {o["id"]: o.get("ended") for o in outcomes}
    # How long after a kill each job its worker held was done (by another worker): the hand-back delay.
    kill_to_done = [ended[job] - kill["at"] for kill in killed for job in kill["jobs"] if ended.get(job)]
    time.sleep(2)
    worker_stats = harness.stats(client)
    return {
        "jobs": jobs,
        "distinct_ids": len(set(ids)),
        "succeeded": sum(o["state"] == "succeeded" for o in outcomes),
        "lost": sum(o["state"] != "succeeded" for o in outcomes),
        "states": sorted({o["state"] for o in outcomes}),
        "duplicates_seen": sum(len(set(o["seen"])) > 1 for o in outcomes),
        "distinct_results": len(rules),
        "kills": len(killed),
        "jobs_rerun": len(rerun),
        "executions_started": sum(tries.values()),
        "executions_completed": int(worker_stats.get("jobs:infer:succeeded", 0)),
        "latency_first_run": harness.summary_ms([o["latency"] for o in once]),
        "latency_rerun": harness.summary_ms([o["latency"] for o in rerun]),
        "runs_killed": sum(len(kill["jobs"]) for kill in killed),
        "kill_to_done": harness.summary_ms(kill_to_done),
        "wall_s": round(wall, 1),
        "sandbox_servers_orphaned": sum(harness.alive(p) for p in orphans),
    }


def _probe_while_down(http: httpx.Client, job_id: str, until: float, probes: dict[str, list[int]],
                      retry_after: set[str], latency: list[float]) -> None:
    """Call every kind of endpoint every 0.2 s until `until`, noting each answer's status, its latency and which
    answered 503 with a Retry-After."""
    calls: dict[str, Callable[[], httpx.Response]] = {
        "POST /check-actions": lambda: http.post("/check-actions", json=check_body("system.REQUEST('area')")),
        "POST /infer-preconditions": lambda: http.post("/infer-preconditions", json=infer_body(seed=7)),
        "GET /jobs/{id}": lambda: http.get(f"/jobs/{job_id}"),
        "GET /ready": lambda: http.get("/ready"),
        "GET /health": lambda: http.get("/health"),
    }
    while time.monotonic() < until:
        for name, call in calls.items():
            t = time.monotonic()
            answer = call()
            latency.append(time.monotonic() - t)
            probes.setdefault(name, []).append(answer.status_code)
            if answer.status_code == 503 and answer.headers.get("Retry-After"):
                retry_after.add(name)
        time.sleep(0.2)


async def _follow(stack: Stack, accepted: list[str], deadline_s: float) -> list[dict[str, Any]]:
    """Every accepted job followed to its end (or lost, or past the deadline)."""
    async with httpx.AsyncClient(base_url=stack.base_url, timeout=30) as http:
        deadline = time.monotonic() + deadline_s

        async def poll(job_id: str) -> dict[str, Any]:
            while time.monotonic() < deadline:
                answer = await http.get(f"/jobs/{job_id}")
                if answer.status_code == 404:
                    return {"id": job_id, "state": "lost (404)"}
                if answer.status_code == 200 and answer.json()["status"] in harness.TERMINAL:
                    return {"id": job_id, "state": answer.json()["status"]}
                await asyncio.sleep(0.25)
            return {"id": job_id, "state": "timed out"}

        return await asyncio.gather(*(poll(j) for j in accepted))


# ---- Redis restart ------------------------------------------------------------------------------------


def redis_restart(stack: Stack, jobs: int, millions: int, down_s: float, kill: bool = False,
                  deadline_s: float = 300) -> dict[str, Any]:
    """Accept `jobs` jobs, take Redis down for `down_s` mid-queue (SIGTERM, or SIGKILL with `kill`), bring
    it back on the same append-only file, and follow every accepted job to its end."""
    stack.start_worker()
    probes: dict[str, list[int]] = {}
    retry_after: set[str] = set()
    probe_latency: list[float] = []
    with stack.http(timeout=30) as http:
        accepted = []
        for i in range(jobs):
            answer = http.post("/infer-preconditions", json=heavy_infer_body(20_000 + i, millions),
                               params={"wait": 0})
            assert answer.status_code in (200, 202), answer.text
            accepted.append(answer.headers["X-Job-Id"])
        wait_until(lambda: harness.stats(stack.redis.client()).get("jobs:infer:succeeded", 0) >= 1, 60,
                   "a first job to finish")
        client = stack.redis.client()
        queued_at_stop = int(client.zcard(MODEL_FREE_QUEUE))
        if kill:
            time.sleep(1.1)  # appendfsync everysec: what was acknowledged more than a second ago is on disk
            stack.redis.kill()  # type: ignore[attr-defined]
        else:
            stack.redis.stop()
        stopped = time.monotonic()
        _probe_while_down(http, accepted[-1], stopped + down_s, probes, retry_after, probe_latency)
        stack.redis.start()
        restarted = time.monotonic()
        wait_until(lambda: http.post("/check-actions", json=check_body("system.REQUEST('city')"),
                                     params={"wait": 5}).status_code == 200, 60, "check-actions after restart")
        first_ok = time.monotonic() - restarted
        wait_until(lambda: http.get("/ready").status_code == 200, 60, "ready after restart")
        ready_after = time.monotonic() - restarted
        queued_after = int(stack.redis.client().zcard(MODEL_FREE_QUEUE))

    outcomes = asyncio.run(_follow(stack, accepted, deadline_s))
    all_done = time.monotonic() - restarted
    return {
        "mode": "SIGKILL" if kill else "SIGTERM",
        "accepted": len(accepted),
        "queued_when_stopped": queued_at_stop,
        "queued_after_restart": queued_after,
        "succeeded": sum(o["state"] == "succeeded" for o in outcomes),
        "lost": sum(o["state"] != "succeeded" for o in outcomes),
        "states": sorted({o["state"] for o in outcomes}),
        "down_s": down_s,
        "answers_while_down": {k: sorted(set(v)) for k, v in probes.items()},
        "503_with_retry_after": sorted(retry_after),
        "probe_latency_while_down": harness.summary_ms(probe_latency),
        "first_200_after_restart_s": round(first_ok, 2),
        "ready_after_restart_s": round(ready_after, 2),
        "all_jobs_done_after_restart_s": round(all_done, 1),
    }


# ---- hostile input ------------------------------------------------------------------------------------


def hostile_input(stack: Stack, canary_dir: Path, concurrency: int = 4) -> dict[str, Any]:
    """Every hostile request of precond/stack/hostile.py over HTTP; the service must answer each with
    its expected status and a clear error, stay up, and write none of the canary files."""
    stack.start_worker()
    worker_pids = stack.worker_pids()
    gateway = harness.gateway_pid(stack)
    cases = hostile_requests(canary_dir)

    async def send(http: httpx.AsyncClient, case: dict[str, Any]) -> dict[str, Any]:
        t = time.monotonic()
        try:
            answer = await http.request(case["method"], case["path"], params=case.get("params"),
                                        headers=case.get("headers"), content=case.get("content"),
                                        json=case.get("json"))
            status, text = answer.status_code, answer.text
        except (httpx.HTTPError, httpx.InvalidURL) as exc:
            status, text = -1, f"{type(exc).__name__}: {exc}"
        return {"name": case["name"], "status": status, "body": text, "seconds": time.monotonic() - t,
                "expect": case["expect"], "check": case.get("check")}

    async def run() -> list[dict[str, Any]]:
        async with httpx.AsyncClient(base_url=stack.base_url, timeout=120) as http:
            return await harness.bounded_gather(concurrency, [functools.partial(send, http, c) for c in cases])

    started = time.monotonic()
    results = asyncio.run(run())
    wall = time.monotonic() - started
    problems = []
    for result in results:
        problem = judge(result)
        if problem:
            problems.append(f"{result['name']}: {problem}")
    with stack.http() as http:
        healthy = http.get("/health").status_code == 200
        still_works = http.post("/check-actions", json=check_body("system.REQUEST('city')"), params={"wait": 10})
    canaries = sorted(str(p) for p in canary_dir.iterdir())
    by_status: dict[str, int] = {}
    for result in results:
        by_status[str(result["status"])] = by_status.get(str(result["status"]), 0) + 1
    return {
        "requests": len(results),
        "by_status": dict(sorted(by_status.items())),
        "problems": problems,
        "canaries_written": canaries,
        "gateway_alive": harness.alive(gateway) and healthy,
        "check_after": still_works.status_code,
        "worker_restarts": len(stack.worker_pids() ^ worker_pids),
        "slowest": harness.summary_ms([r["seconds"] for r in results]),
        "wall_s": round(wall, 1),
        "results": [{k: r[k] for k in ("name", "status", "seconds")} | {"body": r["body"][:300]}
                    for r in results],
    }


def judge(result: dict[str, Any]) -> str | None:
    """Why an answer to a hostile request is not acceptable, or None."""
    status, expect = result["status"], result["expect"]
    if status not in expect:
        return f"status {status}, expected {expect}: {result['body'][:300]}"
    try:
        body = json.loads(result["body"])
    except ValueError:
        return "body is not JSON"
    if "root:x:0:0" in result["body"]:
        return "leaked /etc/passwd"
    if status >= 400:
        error = body.get("error", {})
        if not error.get("type") or not error.get("message"):
            return f"unclear error {error}"
        if error.get("type") == "internal":
            return "internal error"
        if len(result["body"]) > 20_000:
            return f"error body of {len(result['body'])} bytes"
    check = result.get("check")
    if check is not None:
        return check(body)  # type: ignore[no-any-return]
    return None


# ---- fuzzing ------------------------------------------------------------------------------------------


def fuzz(stack: Stack, max_examples: int, seed: int, out: Path, max_time_s: int | None = None) -> dict[str, Any]:
    """schemathesis against openapi/openapi.json, all operations, all phases it runs by default.

    Checks: no 5xx, responses (status code, content type, headers, body) conform to the document."""
    stack.start_worker()
    out.mkdir(parents=True, exist_ok=True)
    checks = ",".join([
        "not_a_server_error", "status_code_conformance", "content_type_conformance",
        "response_headers_conformance", "response_schema_conformance",
    ])
    argv = [
        str(Path(sys.executable).with_name("st")), "run", str(ROOT / "openapi" / "openapi.json"),
        "--url", stack.base_url, "--checks", checks, "--max-examples", str(max_examples), "--seed", str(seed),
        "--workers", "2", "--request-timeout", "60", "--continue-on-failure",
        "--suppress-health-check", "all", "--phases", "examples,fuzzing,stateful",
        "--report", "junit,ndjson", "--report-dir", str(out),
    ]
    if max_time_s:
        argv += ["--max-time", str(max_time_s)]
    started = time.monotonic()
    run = subprocess.run(argv, capture_output=True, text=True, cwd=out, timeout=1200, check=False)
    wall = time.monotonic() - started
    counts = _ndjson_counts(out)
    (out / "schemathesis.txt").write_text(run.stdout + run.stderr)
    with stack.http() as http:
        alive = http.get("/health").status_code == 200
    return {"exit_code": run.returncode, "wall_s": round(wall, 1), **counts, "gateway_alive": alive,
            "summary": _summary_lines(run.stdout)}


def _ndjson_counts(out: Path) -> dict[str, Any]:
    statuses: dict[str, int] = {}
    failures: list[str] = []
    requests = 0
    for path in out.glob("*.ndjson"):
        for line in path.read_text().splitlines():
            _walk(json.loads(line), statuses, failures)
    requests = sum(statuses.values())
    return {"requests": requests, "by_status": dict(sorted(statuses.items())), "failures": sorted(set(failures))}


def _walk(node: Any, statuses: dict[str, int], failures: list[str]) -> None:
    """Collect response status codes and failed checks from schemathesis' event stream (format-agnostic)."""
    if isinstance(node, dict):
        response = node.get("response")
        if isinstance(response, dict) and isinstance(response.get("status_code"), int):
            key = str(response["status_code"])
            statuses[key] = statuses.get(key, 0) + 1
        if node.get("status") in ("failure", "FAILURE") and isinstance(node.get("name"), str):
            failures.append(f"{node['name']}: {str(node.get('message') or node.get('title') or '')[:200]}")
        for value in node.values():
            _walk(value, statuses, failures)
    elif isinstance(node, list):
        for value in node:
            _walk(value, statuses, failures)


def _summary_lines(text: str) -> list[str]:
    lines = [line for line in text.splitlines() if line.strip()]
    return lines[-12:]


# ---- overload -----------------------------------------------------------------------------------------


def overload(stack: Stack, clients: int, duration_s: float, millions: int, wait_s: float = 5) -> dict[str, Any]:
    """`clients` clients keep posting distinct slow infer jobs at one worker (concurrency 1) for
    `duration_s`, while probes measure cache hits, uncached check-actions and /health, and RSS is sampled."""
    stack.start_worker()
    load = _Overload(stack, harness.gateway_pid(stack), next(iter(stack.worker_pids())), clients, duration_s,
                     millions, wait_s)
    with stack.http() as http:
        assert http.post("/check-actions", json=load.cached_body, params={"wait": 10}).status_code == 200
        for i in range(3):  # warm the worker's engine so "before" is a steady state
            http.post("/infer-preconditions", json=heavy_infer_body(29_000 + i, 1), params={"wait": 30})
    load.sample()
    before = {k: v[-1] for k, v in load.rss.items()}
    started = time.monotonic()
    asyncio.run(load.run())
    wall = time.monotonic() - started
    time.sleep(1)
    load.sample()
    return load.report(wall, before)


@dataclass
class _Overload:
    """One overload run: its clients, probes and monitor, and what they measured."""

    stack: Stack
    gateway: int
    worker: int
    clients: int
    duration_s: float
    millions: int
    wait_s: float
    cached_body: dict[str, Any] = field(default_factory=lambda: check_body("system.REQUEST('city')"))
    rss: dict[str, list[int]] = field(default_factory=lambda: {"gateway": [], "worker": []})
    mid: dict[str, int] = field(default_factory=dict)
    statuses: dict[str, int] = field(default_factory=dict)
    retry_after_missing: int = 0
    post_latency: list[float] = field(default_factory=list)
    over_timeout: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    latencies: dict[str, list[float]] = field(
        default_factory=lambda: {"cache_hit": [], "check_actions": [], "health": []})
    probe_status: dict[str, dict[str, int]] = field(
        default_factory=lambda: {"cache_hit": {}, "check_actions": {}, "health": {}})
    max_depth: int = 0
    counter: Iterator[int] = field(default_factory=lambda: iter(range(10**9)))
    end: float = 0.0

    def sample(self) -> None:
        self.rss["gateway"].append(harness.rss_kib(self.gateway))
        self.rss["worker"].append(harness.tree_rss_kib(self.worker))

    async def run(self) -> None:
        self.end = time.monotonic() + self.duration_s
        limits = httpx.Limits(max_connections=self.clients + 8)
        async with httpx.AsyncClient(base_url=self.stack.base_url, timeout=self.wait_s + 10, limits=limits) as http:

            def check() -> Any:
                call = f"system.REQUEST('slot_{next(self.counter)}')"
                return http.post("/check-actions", json=check_body(call), params={"wait": self.wait_s})

            await asyncio.gather(
                *(self.loader(http) for _ in range(self.clients)),
                self.probe("cache_hit", lambda: http.post("/check-actions", json=self.cached_body), 0.05),
                self.probe("check_actions", check, 0.1),
                self.probe("health", lambda: http.get("/health"), 0.2),
                self.monitor(),
            )

    async def loader(self, http: httpx.AsyncClient) -> None:
        """Post distinct slow infer jobs until the end, impatiently after a 429."""
        while time.monotonic() < self.end:
            body = heavy_infer_body(30_000 + next(self.counter), self.millions)
            t = time.monotonic()
            try:
                answer = await http.post("/infer-preconditions", json=body, params={"wait": self.wait_s})
            except httpx.HTTPError as exc:
                self.errors.append(f"{type(exc).__name__}: {exc}")
                continue
            took = time.monotonic() - t
            self.post_latency.append(took)
            if took > self.wait_s + 2:
                self.over_timeout.append(took)
            key = str(answer.status_code)
            self.statuses[key] = self.statuses.get(key, 0) + 1
            if answer.status_code == 429:
                if not answer.headers.get("Retry-After", "").isdigit():
                    self.retry_after_missing += 1
                await asyncio.sleep(0.2)  # impatient clients: far less than Retry-After

    async def probe(self, name: str, request: Any, period: float) -> None:
        while time.monotonic() < self.end:
            t = time.monotonic()
            try:
                answer = await request()
                self.latencies[name].append(time.monotonic() - t)
                key = str(answer.status_code)
                self.probe_status[name][key] = self.probe_status[name].get(key, 0) + 1
            except httpx.HTTPError as exc:
                self.errors.append(f"{name}: {type(exc).__name__}: {exc}")
            await asyncio.sleep(period)

    async def monitor(self) -> None:
        """The queue's depth and the processes' RSS every 0.5 s, and their RSS once at half time."""
        client = self.stack.redis.client()
        half = time.monotonic() + self.duration_s / 2
        while time.monotonic() < self.end:
            if half and time.monotonic() >= half:
                self.mid.update(gateway=harness.rss_kib(self.gateway), worker=harness.tree_rss_kib(self.worker))
                half = 0
            self.max_depth = max(self.max_depth, int(client.zcard(MODEL_FREE_QUEUE)))
            self.sample()
            await asyncio.sleep(0.5)

    def report(self, wall: float, before: dict[str, int]) -> dict[str, Any]:
        after = {k: v[-1] for k, v in self.rss.items()}
        completed = harness.stats(self.stack.redis.client()).get("jobs:infer:succeeded", 0)
        probes = {name: harness.summary_ms(self.latencies[name]) | {"status": self.probe_status[name]}
                  for name in self.latencies}
        return {
            "clients": self.clients,
            "duration_s": round(wall, 1),
            "worker_capacity_jobs_per_s": round(completed / wall, 2),
            "queue_bound": int(self.stack.env.get("PRECOND_QUEUE_MAX_JOBS", "64")),
            "max_queue_depth": self.max_depth,
            "infer_posts": sum(self.statuses.values()),
            "infer_by_status": dict(sorted(self.statuses.items())),
            "429_without_retry_after": self.retry_after_missing,
            "infer_post_latency": harness.summary_ms(self.post_latency),
            "posts_over_wait_plus_2s": len(self.over_timeout),
            "client_errors": self.errors[:10],
            "client_error_count": len(self.errors),
            **probes,
            "rss_mib": {k: {"before": round(before[k] / 1024, 1), "half_time": round(self.mid.get(k, 0) / 1024, 1),
                            "peak": round(max(self.rss[k]) / 1024, 1),
                            "after": round(after[k] / 1024, 1)} for k in self.rss},
        }


# ---- graceful shutdown --------------------------------------------------------------------------------


def graceful_shutdown(stack: Stack, millions: int, drain_covers_job: bool) -> dict[str, Any]:
    """SIGTERM to the only worker while it runs a job. With a drain longer than the job the worker finishes
    it and exits; with a shorter one it hands the job back, and the next worker runs it at once (not after
    the job timeout, which is what a SIGKILLed worker's job waits for)."""
    doomed = stack.start_worker()
    body = heavy_infer_body(seed=40_000 + int(drain_covers_job), millions=millions)
    with stack.http() as http:
        answer = http.post("/infer-preconditions", json=body, params={"wait": 0})
        job_id, location = answer.headers["X-Job-Id"], answer.headers["Location"]
        wait_until(lambda: http.get(location).json()["status"] == "running", 30, "job start")
        time.sleep(0.3)
        doomed.send_signal(signal.SIGTERM)
        term = time.monotonic()
        doomed.wait(60)
        exited = time.monotonic() - term
        state_at_exit = http.get(location).json()["status"]
        if state_at_exit != "succeeded":
            stack.start_worker()
        wait_until(lambda: http.get(location).json()["status"] in harness.TERMINAL, 120, "job end")
        final = http.get(location).json()
        finished = time.monotonic() - term
    tries = harness.arq_job_tries(stack.redis.client(), [job_id])
    return {
        "drain_s": float(stack.env["PRECOND_DRAIN_S"]),
        "worker_exit_code": doomed.returncode,
        "worker_exited_after_s": round(exited, 2),
        "state_when_worker_exited": state_at_exit,
        "final_state": final["status"],
        "runs": tries.get(job_id),
        "done_after_sigterm_s": round(finished, 2),
        "job_timeout_s": float(stack.env["PRECOND_JOB_TIMEOUT_S"]),
    }


def tmp_dir(prefix: str) -> Path:
    return Path(tempfile.mkdtemp(prefix=prefix))
