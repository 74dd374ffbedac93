"""Service latency and throughput on loopback: own redis-server, uvicorn gateway, one `precond worker`.

    python bench/service_bench.py                     # tiny random model (precond/stack/tiny_model.py)
    python bench/service_bench.py --model embedded    # the embedded code model (slow on CPU)
    python bench/service_bench.py --json bench/service.json

Every request carries an API key (two tenants, `quiet` and `flood`). Measures
  * cache-hit throughput: `wrk` (Debian package `wrk`) POSTing one cached check-actions body with a Lua
    script; falls back to an httpx asyncio client when wrk is not installed (the table says which);
  * check-actions latency, uncached: sequential requests whose calls differ, so every one is a new job;
  * the same against a stored precondition set, with a history of 40 events (what a dialog system sends);
  * both again timed by `wrk -c1` (one request at a time, a new call in each), when wrk is installed: the
    service's latency without this script's httpx client, whose own CPU is some 2 ms a request on 2 cores;
    the example's spec is one `precond convert sgd` writes and its rules are ones the restricted interpreter
    evaluates, so the gateway judges these checks itself (`judged_by: interpreter`); the row `... sandbox` sends
    the same check with one more rule the interpreter does not evaluate (always true, on an action not called),
    which takes the queue, a worker and the sandbox: the two paths paired by spec, in turn;
  * check-actions latency, uncached, on the queue path (the `... sandbox` row's body), timed by httpx as the first two;
  * Redis commands per check on the queue path: `INFO commandstats` of the stack's Redis around 50 uncached
    checks that take it (the sandbox row's body), counted per command;
  * next-action latency through the gateway, uncached (a different seed per request);
  * fairness: the quiet tenant's uncached check-actions latency alone, and while the other tenant has
    `--flood` check-actions jobs queued (and how long those take to drain: what a first-come-first-served
    queue would have made the quiet tenant wait).
`--root DIR` runs gateway and worker from another checkout (e.g. `git archive HEAD | tar -x -C DIR`); given
twice or more, every checkout is measured in turn in one invocation and the table has a column per checkout
(`--root OLD --root .`: before and after on the same machine). `--interleave` keeps every checkout's stack up
at once and sends each uncached check to every checkout in turn (wrk: one-second runs in turn), so that a
machine whose speed drifts within seconds slows every checkout alike (the other rows are still measured one
checkout after the other, the idle stacks up beside them). `--env K=V` passes settings (e.g. PRECOND_CHECK_POLL_S=0.05).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
sys.path.insert(0, str(ROOT))

from precond.stack.local import free_port, wait_until  # noqa: E402

TENANTS = ("quiet", "flood")


def make_keys(path: Path) -> dict[str, str]:
    from precond.gateway.api_keys import KeyRecord, digest, new_key, write_records

    keys, records = {}, []
    for tenant in TENANTS:
        key_id, key = new_key()
        keys[tenant] = key
        records.append(KeyRecord(key_id, tenant, digest(key), time.strftime("%Y-%m-%dT%H:%M:%S+00:00")))
    write_records(path, records)
    return keys


def auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@contextmanager
def stack(args: argparse.Namespace, tmp: Path) -> Iterator[str]:
    """Redis, gateway and one worker as child processes; yields the gateway's base URL."""
    redis_port, http_port = free_port(), free_port()
    env = {
        **os.environ,
        "PRECOND_SECRET": "bench-secret",
        "PRECOND_API_KEYS_FILE": str(tmp / "keys.jsonl"),
        "PRECOND_TENANT_RATE_PER_S": "100000",
        "PRECOND_TENANT_BURST": "100000",
        "PRECOND_TENANT_MAX_JOBS": str(args.flood + 100),
        "PRECOND_QUEUE_MAX_JOBS": str(args.flood + 100),
        "REDIS_URL": f"redis://127.0.0.1:{redis_port}/0",
        "PYTHONPATH": str(args.root),
        "OMP_NUM_THREADS": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "MODEL_THREADS": "1",
    }
    if args.model == "tiny":
        from precond.stack.tiny_model import build_tiny_model

        env["MODEL_PATH"] = str(build_tiny_model(tmp / "tiny-model"))
    else:
        env["MODEL_PATH"] = args.model
    env.update(kv.split("=", 1) for kv in args.env)
    logs = (tmp / "stack.log").open("wb")
    redis_server = shutil.which("redis-server") or "/usr/bin/redis-server"
    argvs = [
        [redis_server, "--port", str(redis_port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--dir", str(tmp)],
        [sys.executable, "-m", "uvicorn", *root_gateway_args(args.root, args.gateway_processes, env),
         "--port", str(http_port), "--log-level", "warning", "--no-access-log"],
        [sys.executable, "-c", f"from {layout(args.root, 'cli')}.main import app; app()", "worker"],
    ]
    processes: list[subprocess.Popen[bytes]] = []
    try:
        for argv in argvs:
            processes.append(subprocess.Popen(argv, env=env, cwd=args.root, stdout=logs, stderr=subprocess.STDOUT))
            if argv[0] == redis_server:
                time.sleep(0.3)
        base = f"http://127.0.0.1:{http_port}"
        (tmp / "redis-port").write_text(str(redis_port))
        wait_until(lambda: httpx.get(f"{base}/ready", timeout=2).status_code == 200, 300, "a ready worker")
        yield base
    finally:
        for process in reversed(processes):
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()


def layout(root: Path, package: str) -> str:
    """A package's module path in `root`: under `precond` now; at the top level in checkouts older than that."""
    if (root / "precond").is_dir():
        return f"precond.{'gateway' if package == 'service' else package}"
    return package


def root_gateway_args(root: Path, processes: int, env: dict[str, str]) -> list[str]:
    """The uvicorn options of `root`'s own gateway (a checkout's gateway may start differently)."""
    code = (f"import json, sys; from {layout(root, 'service')}.server import gateway_args as a; "
            "print(json.dumps(a(int(sys.argv[1]))))")
    out = subprocess.run([sys.executable, "-c", code, str(processes)], env=env, cwd=root, capture_output=True,
                         text=True, check=True).stdout
    return list(json.loads(out))


def percentile(samples: list[float], q: float) -> float:
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def latencies(base: str, path: str, bodies: list[dict[str, Any]], warmup: int, key: str) -> dict[str, float]:
    """Sequential POSTs; every body must be new to the cache. Milliseconds."""
    with httpx.Client(base_url=base, timeout=300, headers=auth(key)) as client:
        seconds = [timed_post(client, path, body) for body in bodies]
    return summary(seconds[warmup:])


def timed_post(client: httpx.Client, path: str, body: dict[str, Any]) -> float:
    """Seconds one POST took to answer 200 (anything else ends the benchmark)."""
    started = time.perf_counter()
    answer = client.post(path, json=body, params={"wait": 300})
    elapsed = time.perf_counter() - started
    if answer.status_code != 200:
        raise SystemExit(f"{path}: {answer.status_code} {answer.text[:300]}")
    return elapsed


def summary(seconds: list[float]) -> dict[str, float]:
    ms = [s * 1000 for s in seconds]
    return {"n": len(ms), "p50_ms": percentile(ms, 50), "p95_ms": percentile(ms, 95), "p99_ms": percentile(ms, 99),
            "mean_ms": statistics.mean(ms)}


def dialog_events(n: int) -> list[dict[str, Any]]:
    """A dialog of `n` events: the user gives slots, the system asks for the next (literals only)."""
    slots = ["city", "cuisine", "price_range", "date", "time", "party_size", "location", "phone_number"]
    events: list[dict[str, Any]] = [{"actor": "user", "act": "INFORM_INTENT", "args": ["FindRestaurants"]}]
    while len(events) < n:
        slot = slots[len(events) % len(slots)]
        events.append({"actor": "system", "act": "REQUEST", "args": [slot]})
        events.append({"actor": "user", "act": "INFORM", "args": [slot]})
    return events[:n]


def stored_set_checks(base: str, check: dict[str, Any], args: argparse.Namespace, key: str) -> dict[str, float]:
    """check-actions naming a stored set (its rules are the example's) over a 40-event history, uncached."""
    return latencies(base, "/check-actions", stored_set_bodies(base, check, args, key), warmup=5, key=key)


def stored_set_bodies(base: str, check: dict[str, Any], args: argparse.Namespace, key: str) -> list[dict[str, Any]]:
    """Stores the example's rules as a set; checks naming it, each with a new call after the same 40 events."""
    template = stored_set_template(base, check, key)
    return [{**template, "calls": [f"system.REQUEST('set_{i}')"]} for i in range(args.check_n + 5)]


def stored_set_template(base: str, check: dict[str, Any], key: str) -> dict[str, Any]:
    """A check naming a new stored set of the example's rules, after 40 events (its calls still to add)."""
    with httpx.Client(base_url=base, timeout=60, headers=auth(key)) as client:
        rules = {"spec": check["spec"], "preconditions": check["preconditions"]}
        answer = client.post("/precondition-sets", json=rules)
        if answer.status_code != 201:
            raise SystemExit(f"/precondition-sets: {answer.status_code} {answer.text[:300]}")
    return {"precondition_set": answer.json()["id"], "history": dialog_events(40)}


NOT_INTERPRETED = {"SYSTEM.GOODBYE": ["str(1) == '1'"]}
"""A rule that always holds on an action the checks do not call, outside the restricted interpreter's grammar (it
calls `str`): the check takes the queue and the sandbox, its verdicts unchanged."""


def sandboxed(check: dict[str, Any]) -> dict[str, Any]:
    return {**check, "preconditions": {**check["preconditions"], **NOT_INTERPRETED}}


def redis_commands_per_check(base: str, tmp: Path, check: dict[str, Any], key: str, n: int = 50) -> dict[str, Any]:
    """Commands the stack's Redis ran per uncached check on the queue path (`INFO commandstats` before and after
    `n` sequential checks; the worker's idle reads of its queues, 1 a second, are in the count)."""
    import redis

    server = redis.Redis(port=int((tmp / "redis-port").read_text()))
    bodies = [{**sandboxed(check), "calls": [f"system.REQUEST('redis_{i}')"]} for i in range(n)]

    def stats() -> dict[str, int]:
        return {name.removeprefix("cmdstat_"): int(v["calls"]) for name, v in server.info("commandstats").items()}

    before = stats()
    with httpx.Client(base_url=base, timeout=300, headers=auth(key)) as client:
        for body in bodies:
            timed_post(client, "/check-actions", body)
    after = stats()
    per = {name: (after[name] - before.get(name, 0)) / n for name in after if after[name] != before.get(name, 0)}
    return {"n": n, "per_check": sum(per.values()), "by_command": dict(sorted(per.items(), key=lambda kv: -kv[1]))}


def uncached_bodies(check: dict[str, Any], args: argparse.Namespace, tag: str = "slot") -> list[dict[str, Any]]:
    """check-actions bodies with one new call each: a fresh job every time."""
    return [{**check, "calls": [f"system.REQUEST('{tag}_{i}')"]} for i in range(args.check_n + 5)]


def interleaved_checks(stacks: list[tuple[str, dict[str, str]]], check: dict[str, Any], args: argparse.Namespace
                       ) -> list[dict[str, dict[str, float]]]:
    """The two uncached check rows of every checkout, each request sent to every stack in turn (the order
    rotated at each round): on a machine whose speed drifts within seconds, every checkout sees the same
    drift, where measured one after the other a checkout could get a slow phase and another a fast one."""
    clients = [httpx.Client(base_url=base, timeout=300, headers=auth(keys["quiet"])) for base, keys in stacks]
    try:
        plain, queued = uncached_bodies(check, args), uncached_bodies(sandboxed(check), args, "queued")
        stored = [stored_set_bodies(base, check, args, keys["quiet"]) for base, keys in stacks]
        rows: list[dict[str, dict[str, float]]] = [{} for _ in stacks]
        for row, bodies in (("check_actions_uncached", [plain] * len(stacks)), ("stored_set_40_events", stored),
                            ("check_actions_uncached_queue", [queued] * len(stacks))):
            seconds: list[list[float]] = [[] for _ in stacks]
            for i in range(args.check_n + 5):
                for step in range(len(stacks)):
                    k = (i + step) % len(stacks)
                    seconds[k].append(timed_post(clients[k], "/check-actions", bodies[k][i]))
            for k, taken in enumerate(seconds):
                rows[k][row] = summary(taken[5:])
        return rows
    finally:
        for client in clients:
            client.close()


def fairness(base: str, check: dict[str, Any], keys: dict[str, str], args: argparse.Namespace) -> dict[str, Any]:
    """The quiet tenant's latency alone, then behind `args.flood` queued jobs of the other tenant (checks that
    take the queue: `check` is the sandbox row's body)."""
    def quiet(tag: str) -> dict[str, float]:
        bodies = [{**check, "calls": [f"system.REQUEST('{tag}_{i}')"]} for i in range(args.fair_n + 2)]
        return latencies(base, "/check-actions", bodies, warmup=2, key=keys["quiet"])

    alone = quiet("alone")
    with httpx.Client(base_url=base, timeout=60, headers=auth(keys["flood"])) as flood:
        started = time.perf_counter()
        for i in range(args.flood):
            answer = flood.post("/check-actions", json={**check, "calls": [f"system.REQUEST('flood_{i}')"]},
                                params={"wait": 0})
            assert answer.status_code in (200, 202), answer.text
        last = answer.headers["X-Job-Id"]
        flooded = quiet("flooded")
        wait_until(lambda: flood.get(f"/jobs/{last}").json()["status"] == "succeeded", 600, "the flood")
        drained = time.perf_counter() - started
    return {"flood_jobs": args.flood, "quiet_alone": alone, "quiet_during_flood": flooded,
            "flood_drain_s": drained}


WRK_LUA = """wrk.method = "POST"
wrk.headers["Content-Type"] = "application/json"
wrk.headers["Authorization"] = "Bearer {key}"
wrk.body = io.open("{body}"):read("*a")
"""


WRK_SEQUENTIAL_LUA = r"""local pre, post = [=======[{pre}]=======], [=======[{post}]=======]
local ffi = require("ffi")
ffi.cdef[[ typedef struct {{ long s; long ns; }} bench_time; int clock_gettime(int, bench_time *); ]]
local clock = ffi.new("bench_time")
local function now_us() ffi.C.clock_gettime(1, clock); return tonumber(clock.s) * 1e6 + tonumber(clock.ns) / 1e3 end
local threads, tag, i, sent = {{}}, "", 0, 0
samples = {{}}
wrk.method = "POST"
wrk.path = "/check-actions?wait=300"
wrk.headers["Content-Type"] = "application/json"
wrk.headers["Authorization"] = "Bearer {key}"
function setup(thread) table.insert(threads, thread) end
function init(args) tag = args[1] end
function request()
  i = i + 1
  sent = now_us()
  return wrk.format(nil, nil, nil, pre .. tag .. "_" .. i .. post)
end
function response(status, headers, body)
  if status == 200 then samples[#samples + 1] = math.floor(now_us() - sent) end
end
function done(summary, latency, requests)
  local e = summary.errors
  io.write(string.format("errors %d\n", e.connect + e.read + e.write + e.status + e.timeout))
  for _, thread in ipairs(threads) do
    for _, us in ipairs(thread:get("samples")) do io.write(string.format("%d\n", us)) end
  end
end
"""
"""One connection, one request at a time, each with a new call (`tag`_`i`): a check no cache holds. Each
answer's latency (write of the request to the end of the answer, CLOCK_MONOTONIC through LuaJIT's ffi) is
printed by `done`, so that short runs can be merged (wrk's own histogram cannot be read from its scripts)."""

CALL = "@@CALL@@"


def wrk_sequential_rows(stacks: list[tuple[str, dict[str, str]]], check: dict[str, Any], args: argparse.Namespace,
                        tmp: Path) -> list[dict[str, dict[str, float]]]:
    """The two uncached check rows again, timed by wrk (C) rather than this script's httpx client, whose own
    CPU (some 2 ms a request on a 2-core machine) is not the service's latency: one-second runs of
    `wrk -c1`, every checkout in turn (the order rotated), `--wrk-seconds` of them per checkout and row."""
    rows: list[dict[str, dict[str, float]]] = [{} for _ in stacks]
    templates = {
        "check_actions_uncached_wrk": [{**check} for _ in stacks],
        "check_actions_uncached_sandbox_wrk": [sandboxed(check) for _ in stacks],
        "stored_set_40_events_wrk": [stored_set_template(base, check, keys["quiet"]) for base, keys in stacks],
    }
    for row, bodies in templates.items():
        scripts = []
        for k, ((_, keys), body) in enumerate(zip(stacks, bodies, strict=True)):
            pre, post = json.dumps({**body, "calls": [f"system.REQUEST('{CALL}')"]}).split(CALL)
            scripts.append(tmp / f"{row}-{k}.lua")
            scripts[-1].write_text(WRK_SEQUENTIAL_LUA.format(pre=pre, post=post, key=keys["quiet"]))
        samples: list[list[float]] = [[] for _ in stacks]
        for r in range(args.wrk_seconds):
            for step in range(len(stacks)):
                k = (r + step) % len(stacks)
                tag = f"{row}{r}-{time.time()}"
                argv = ["wrk", "-t1", "-c1", "-d1s", "-s", str(scripts[k]), stacks[k][0], "--", tag]
                out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
                samples[k] += _seconds(out)
        for k, taken in enumerate(samples):
            rows[k][row] = summary(taken)
    return rows


def _seconds(out: str) -> list[float]:
    """The latencies a `WRK_SEQUENTIAL_LUA` run printed; a failed request ends the benchmark."""
    lines = out.splitlines()
    errors = next((line.split()[1] for line in lines if line.startswith("errors ")), "?")
    if errors != "0":
        raise SystemExit(f"wrk: {errors} requests failed")
    return [int(line) / 1e6 for line in lines if line.isdigit()]


def cache_hits_wrk(base: str, body_file: Path, tmp: Path, args: argparse.Namespace, key: str) -> dict[str, Any]:
    script = tmp / "post.lua"
    script.write_text(WRK_LUA.format(body=body_file, key=key))
    argv = ["wrk", f"-t{args.threads}", f"-c{args.connections}", f"-d{args.duration}s", "--latency", "-s",
            str(script), f"{base}/check-actions"]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    result: dict[str, Any] = {"tool": f"wrk -t{args.threads} -c{args.connections} -d{args.duration}s"}
    for line in out.splitlines():
        words = line.split()
        if line.startswith("Requests/sec:"):
            result["requests_per_s"] = float(words[1])
        elif words[:1] in (["50%"], ["90%"], ["99%"]):
            result[f"p{words[0][:-1]}_ms"] = _ms(words[1])
        elif "Non-2xx" in line or "Socket errors" in line:
            result.setdefault("errors", []).append(line.strip())
    return result


def interpreter_throughput_wrk(base: str, check: dict[str, Any], tmp: Path, args: argparse.Namespace,
                               key: str) -> dict[str, Any]:
    """Checks the gateway judges itself, each with a new call, `wrk -t{threads} -c{connections}`: requests/s."""
    pre, post = json.dumps({**check, "calls": [f"system.REQUEST('{CALL}')"]}).split(CALL)
    script = tmp / "interpreter.lua"
    script.write_text(WRK_SEQUENTIAL_LUA.format(pre=pre, post=post, key=key))
    argv = ["wrk", f"-t{args.threads}", f"-c{args.connections}", f"-d{args.duration}s", "-s", str(script), base,
            "--", f"throughput{time.time()}"]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    rate = next(float(line.split()[1]) for line in out.splitlines() if line.startswith("Requests/sec:"))
    errors = next((line.split()[1] for line in out.splitlines() if line.startswith("errors ")), "?")
    return {"tool": f"wrk -t{args.threads} -c{args.connections} -d{args.duration}s", "requests_per_s": rate,
            "errors": errors}


def _ms(text: str) -> float:
    for unit, factor in (("ms", 1.0), ("us", 0.001), ("s", 1000.0)):
        if text.endswith(unit):
            return float(text[: -len(unit)]) * factor
    return float(text)


def cache_hits_httpx(base: str, body: dict[str, Any], args: argparse.Namespace, key: str) -> dict[str, Any]:
    async def run() -> tuple[int, list[float]]:
        done, samples = 0, []
        deadline = time.perf_counter() + args.duration
        limits = httpx.Limits(max_connections=args.connections)
        async with httpx.AsyncClient(base_url=base, limits=limits, timeout=30, headers=auth(key)) as client:

            async def loop() -> None:
                nonlocal done
                while time.perf_counter() < deadline:
                    started = time.perf_counter()
                    answer = await client.post("/check-actions", json=body)
                    assert answer.status_code == 200, answer.text
                    samples.append((time.perf_counter() - started) * 1000)
                    done += 1

            await asyncio.gather(*(loop() for _ in range(args.connections)))
        return done, samples

    done, samples = asyncio.run(run())
    return {
        "tool": f"httpx asyncio, {args.connections} connections, {args.duration}s (wrk not installed)",
        "requests_per_s": done / args.duration,
        "p50_ms": percentile(samples, 50),
        "p99_ms": percentile(samples, 99),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="tiny", help='"tiny" (random test model), "embedded", or a path')
    parser.add_argument("--root", type=Path, action="append",
                        help="checkout to run gateway and worker from (repeat to compare; default: this one)")
    parser.add_argument("--env", action="append", default=[], metavar="K=V", help="extra settings")
    parser.add_argument("--check-n", type=int, default=200, help="uncached check-actions requests")
    parser.add_argument("--next-n", type=int, default=30, help="uncached next-action requests (0: no such row)")
    parser.add_argument("--duration", type=int, default=10, help="seconds of cache-hit load")
    parser.add_argument("--wrk-seconds", type=int, default=10,
                        help="seconds of the uncached rows timed by wrk, per checkout and row (0: none)")
    parser.add_argument("--connections", type=int, default=32)
    parser.add_argument("--threads", type=int, default=2, help="wrk threads")
    parser.add_argument("--flood", type=int, default=500, help="jobs the flooding tenant queues at once")
    parser.add_argument("--fair-n", type=int, default=50, help="the quiet tenant's requests, alone and flooded")
    parser.add_argument("--gateway-processes", type=int, default=1,
                        help="gateway processes behind the port (PRECOND_GATEWAY_PROCESSES)")
    parser.add_argument("--interleave", action="store_true",
                        help="with several --root: all stacks up at once, the uncached check rows measured with "
                        "each request sent to every checkout in turn")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    roots = [root.resolve() for root in args.root or [ROOT]]

    check = json.loads((EXAMPLES / "check-actions.json").read_text())
    next_action = json.loads((EXAMPLES / "next-action.json").read_text())
    runs = []
    with ExitStack() as running:
        stacks = [start(root, args, running) for root in roots] if args.interleave else []
        interleaved = (interleaved_checks([(base, keys) for base, _, keys in stacks], check, args) if stacks
                       else [{} for _ in roots])
        if stacks and shutil.which("wrk") and args.wrk_seconds > 0:
            timed = wrk_sequential_rows([(base, keys) for base, _, keys in stacks], check, args, stacks[0][1])
            interleaved = [{**a, **b} for a, b in zip(interleaved, timed, strict=True)]
        for index, root in enumerate(roots):
            results: dict[str, Any] = {"model": args.model, "root": str(root), "env": args.env,
                                       "cpus": os.cpu_count(), "gateway_processes": args.gateway_processes,
                                       "interleaved": bool(stacks), **interleaved[index]}
            with ExitStack() as one:
                base, tmp, keys = stacks[index] if stacks else start(root, args, one)
                measure(base, tmp, keys, check, next_action, args, results)
            runs.append(results)
    report(runs, args)


def start(root: Path, args: argparse.Namespace, running: ExitStack) -> tuple[str, Path, dict[str, str]]:
    """A stack running `root`'s gateway and worker until `running` closes: its URL, directory and keys."""
    tmp = Path(running.enter_context(tempfile.TemporaryDirectory(prefix="service-bench-")))
    keys = make_keys(tmp / "keys.jsonl")
    return running.enter_context(stack(argparse.Namespace(**{**vars(args), "root": root}), tmp)), tmp, keys


def measure(base: str, tmp: Path, keys: dict[str, str], check: dict[str, Any], next_action: dict[str, Any],
            args: argparse.Namespace, results: dict[str, Any]) -> None:
    key = keys["quiet"]
    # check-actions, uncached: one new call per request (a fresh job each time), then against a stored set.
    if "check_actions_uncached" not in results:  # measured interleaved already
        results["check_actions_uncached"] = latencies(base, "/check-actions", uncached_bodies(check, args), warmup=5,
                                                      key=key)
        results["stored_set_40_events"] = stored_set_checks(base, check, args, key)
        results["check_actions_uncached_queue"] = latencies(
            base, "/check-actions", uncached_bodies(sandboxed(check), args, "queued"), warmup=5, key=key)
        if shutil.which("wrk") and args.wrk_seconds > 0:
            results.update(wrk_sequential_rows([(base, keys)], check, args, tmp)[0])
    # next-action, uncached: a new seed per request; 5 sampling attempts of up to 32 tokens (defaults).
    if args.next_n > 0:
        bodies = [{**next_action, "options": {"seed": i}} for i in range(args.next_n + 2)]
        results["next_action_uncached"] = latencies(base, "/next-action", bodies, warmup=2, key=key)
    # cache hits: a check that takes the queue, cached after its first answer (one the gateway judges itself is
    # never cached: judging it costs less than reading the cache)
    body_file = tmp / "body.json"
    body_file.write_text(json.dumps({**sandboxed(check), "calls": ["system.REQUEST('slot_0')"]}))
    with httpx.Client(base_url=base, timeout=300, headers=auth(key)) as client:
        timed_post(client, "/check-actions", json.loads(body_file.read_text()))
    if shutil.which("wrk"):
        results["interpreter_throughput"] = interpreter_throughput_wrk(base, check, tmp, args, key)
    if shutil.which("wrk"):
        results["cache_hit"] = cache_hits_wrk(base, body_file, tmp, args, key)
    else:
        results["cache_hit"] = cache_hits_httpx(base, json.loads(body_file.read_text()), args, key)
    results["fairness"] = fairness(base, sandboxed(check), keys, args)
    results["redis_commands"] = redis_commands_per_check(base, tmp, check, key)
    results["load_average"] = os.getloadavg()


def rows_of(results: dict[str, Any]) -> list[tuple[str, str]]:
    """(row label, cell) pairs of one checkout's results."""
    hit = results["cache_hit"]
    rows = [("cache hit, check-actions, queue path (" + hit["tool"] + ")",
             f"{hit['requests_per_s']:.0f} req/s, p50 {hit['p50_ms']:.1f} ms, p99 {hit.get('p99_ms', 0):.1f} ms")]
    for key, label in (("check_actions_uncached", "check-actions, uncached"),
                       ("stored_set_40_events", "check-actions, stored set, 40 events, uncached"),
                       ("check_actions_uncached_queue", "check-actions, uncached, queue path (sandbox row's body)"),
                       ("check_actions_uncached_wrk", "check-actions, uncached, wrk -c1"),
                       ("check_actions_uncached_sandbox_wrk", "check-actions, uncached, wrk -c1, sandbox"),
                       ("stored_set_40_events_wrk", "check-actions, stored set, 40 events, uncached, wrk -c1"),
                       ("next_action_uncached", "next-action, uncached")):
        if key not in results:  # --next-n 0, --wrk-seconds 0 or no wrk
            continue
        r = results[key]
        how = "interleaved" if results.get("interleaved") and key != "next_action_uncached" else "sequential"
        rows.append((f"{label} (n={r['n']} {how})", f"p50 {r['p50_ms']:.2f} ms, p95 {r['p95_ms']:.2f} ms, "
                                                   f"p99 {r['p99_ms']:.2f} ms"))
    if "interpreter_throughput" in results:
        r = results["interpreter_throughput"]
        rows.append((f"check-actions judged in the gateway, a new call each ({r['tool']})",
                     f"{r['requests_per_s']:.0f} req/s ({r['errors']} errors)"))
    fair = results["fairness"]
    for key, label in (("quiet_alone", "quiet tenant, alone"), ("quiet_during_flood", "quiet tenant, flooded")):
        r = fair[key]
        rows.append((f"{label} (n={r['n']})", f"p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms"))
    rows.append((f"{fair['flood_jobs']} flood jobs drained", f"{fair['flood_drain_s']:.1f} s"))
    commands = results["redis_commands"]
    top = ", ".join(f"{name} {count:g}" for name, count in list(commands["by_command"].items())[:6])
    rows.append((f"Redis commands per check, queue path (n={commands['n']})", f"{commands['per_check']:.1f} ({top})"))
    return rows


def report(runs: list[dict[str, Any]], args: argparse.Namespace) -> None:
    table = [rows_of(results) for results in runs]
    header = ("", *(str(Path(results["root"]).name) or "/" for results in runs))
    lines = [header] + [(label, *(column[i][1] for column in table)) for i, (label, _) in enumerate(table[0])]
    width = [max(len(line[i]) for line in lines) for i in range(len(header))]
    print(f"model: {args.model}; env: {args.env or '-'}; gateway processes: {args.gateway_processes}; "
          f"roots: {', '.join(r['root'] for r in runs)}")
    print("load average after each: " + "; ".join(str(r["load_average"]) for r in runs))
    for line in lines:
        print("  ".join(cell.ljust(w) for cell, w in zip(line, width, strict=True)))
    for results in runs:
        if results["cache_hit"].get("errors"):
            print(f"wrk ({results['root']}):", "; ".join(results["cache_hit"]["errors"]))
    if args.json:
        args.json.write_text(json.dumps(runs, indent=2) + "\n")


if __name__ == "__main__":
    main()
