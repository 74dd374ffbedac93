"""Real Redis, real worker processes and a real uvicorn gateway, each on free ports in temp dirs.

Every piece runs as its own process so tests can stop Redis, SIGKILL a worker or restart things the way an
operator would. Workers run the production engine (`engine.factory.build_engine`) with the real sandbox;
their code model is the tiny random model of precond/stack/tiny_model.py (`MODEL_PATH`), whose output is noise, so
model jobs end in real rejections rather than in useful rules.

Request bodies are the ones in examples/ (SGD Restaurants_1: its spec program and two demonstrations).
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import httpx
import redis
from redis.asyncio import Redis as AsyncRedis

from precond.gateway.server import gateway_args
from precond.jobs.redis_roles import ROLES, acl_lines, password_file

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = {
    name: json.loads((ROOT / "examples" / f"{name}.json").read_text())
    for name in ("infer-enumerate", "infer-model", "next-action", "check-actions")
}
SPEC: str = EXAMPLES["infer-enumerate"]["spec"]
DEMOS: list[str] = EXAMPLES["infer-enumerate"]["demonstrations"]
RULES: dict[str, list[str]] = EXAMPLES["check-actions"]["preconditions"]
"""Hand-written rules of SPEC that every call of DEMOS satisfies: what a stored set needs (one without rules is
refused)."""
HEAVY_STATEMENT = "heavy = sum(range({n}))\n"
"""Legal, CPU-bound demonstration code: slows every sandbox run of the demonstration down (about 15 ms per
million on this project's CI machines), well within the sandbox's limits."""


def example(name: str) -> dict[str, Any]:
    body: dict[str, Any] = copy.deepcopy(EXAMPLES[name])
    return body


def infer_body(seed: int = 0, **changes: Any) -> dict[str, Any]:
    """A model-free (enumerate-only) inference on the SGD demonstrations: real, and done in about a second."""
    body = example("infer-enumerate")
    body["options"]["seed"] = seed  # unused by enumeration, but part of the job id: a fresh job per seed
    body.update(changes)
    return body


def heavy_infer_body(seed: int, millions: int) -> dict[str, Any]:
    """An enumerate-only inference whose first demonstration burns CPU each time the sandbox runs it."""
    anchor = "system = SYSTEM(user)\n"
    first = DEMOS[0].replace(anchor, anchor + HEAVY_STATEMENT.format(n=millions * 1_000_000), 1)
    return infer_body(seed, demonstrations=[first])


def slow_model_body(seed: int) -> dict[str, Any]:
    """A model inference long enough to be caught running (tens of seconds with the tiny model): 64 samples
    of 256 tokens per prompt. The engine polls its cancel predicate between decode steps."""
    return {
        "spec": SPEC,
        "demonstrations": DEMOS,
        "actions": ["SYSTEM.REQUEST", "SYSTEM.INFORM"],
        "options": {
            "generators": ["model"],
            "samples_per_prompt": 64,
            "prompts_per_action": 2,
            "max_new_tokens": 256,
            "seed": seed,
        },
    }


def check_body(*calls: str) -> dict[str, Any]:
    body = example("check-actions")
    if calls:
        body["calls"] = list(calls)
    return body


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if predicate():
                return
        except (OSError, redis.RedisError, httpx.HTTPError):
            pass
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@dataclass
class RedisServer:
    directory: Path
    port: int = field(default_factory=free_port)
    process: subprocess.Popen[bytes] | None = None
    password: str | None = None
    config: tuple[str, ...] = ()
    """More redis-server options, e.g. `("--maxmemory", "2mb", "--maxmemory-policy", "allkeys-lru")`."""
    user: str | None = None
    """The user `client` names (with `password`), where the server has users of its own (`acl`)."""
    acl: str = ""
    """The server's ACL lines (precond/jobs/redis_roles.py), read on standard input as compose passes them."""

    @property
    def url(self) -> str:
        """Without the password: the stack hands it over in a file (`PRECOND_REDIS_PASSWORD_FILE`)."""
        return f"redis://127.0.0.1:{self.port}/0"

    def client(self) -> redis.Redis[bytes]:
        return redis.Redis(port=self.port, username=self.user, password=self.password, socket_timeout=2)

    def run(self, scenario: Callable[[AsyncRedis[bytes]], Awaitable[None]]) -> None:
        """Runs an async scenario with a client of this server, closed after it whatever happens: the queue's
        and the stores' tests speak to Redis as the gateway and the worker do, through redis-py's asyncio client."""
        async def main() -> None:
            client: AsyncRedis[bytes] = AsyncRedis(port=self.port, username=self.user, password=self.password)
            try:
                await scenario(client)
            finally:
                await client.aclose()  # type: ignore[attr-defined]

        asyncio.run(main())

    def argv(self, persistence: list[str]) -> list[str]:
        argv = ["/usr/bin/redis-server", *(["-"] if self.acl else []), "--port", str(self.port),
                "--bind", "127.0.0.1", "--dir", str(self.directory), *persistence, *self.config]
        return argv if self.password is None or self.acl else [*argv, "--requirepass", self.password]

    def start(self) -> None:
        self.process = subprocess.Popen(self.argv(["--save", "", "--appendonly", "no"]), stdout=subprocess.DEVNULL,
                                        stdin=subprocess.PIPE if self.acl else None)
        if self.process.stdin is not None:
            self.process.stdin.write(self.acl.encode())
            self.process.stdin.close()
        wait_until(lambda: self.client().ping(), 10, "redis-server")

    def stop(self) -> None:
        if self.process:
            self.process.terminate()
            self.process.wait(10)


@dataclass
class Stack:
    """Redis + gateway + workers sharing one environment (the settings under test)."""

    redis: RedisServer
    env: dict[str, str]
    logs: Path
    port: int = field(default_factory=free_port)
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)
    cache_redis: RedisServer | None = None
    """A cache Redis of its own (`PRECOND_CACHE_REDIS_URL`); None: the cache shares the queue Redis."""
    roles: dict[str, dict[str, str]] = field(default_factory=dict)
    """Per process kind (`gateway`, `worker`), settings over `env`: its own Redis users (`make_stack(roles=)`)."""

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def http(self, timeout: float = 30) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=timeout)

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        log = (self.logs / f"{name}-{len(self.processes)}.log").open("wb")
        process = subprocess.Popen(argv, env={**self.env, **self.roles.get(name, {})}, cwd=ROOT, stdout=log,
                                   stderr=subprocess.STDOUT,
                                   start_new_session=True)  # its own process group: stopped with what it started
        self.processes.append(process)
        return process

    def start_gateway(self) -> None:
        processes = int(self.env.get("PRECOND_GATEWAY_PROCESSES", "1"))
        argv = [sys.executable, "-m", "uvicorn", *gateway_args(processes), "--port", str(self.port)]
        self._spawn("gateway", [*argv, "--log-level", "warning"])
        wait_until(lambda: self.http().get("/health").status_code == 200, 20, "gateway")

    def start_worker(self) -> subprocess.Popen[bytes]:
        before = self.worker_pids()
        process = self._spawn("worker", [sys.executable, "-m", "precond.worker.runner"])
        wait_until(lambda: self.worker_pids() - before, 60, "worker heartbeat")
        return process

    def heartbeats(self) -> list[dict[str, object]]:
        client = self.redis.client()
        beats = list(client.scan_iter(match="precond:worker:*"))  # SCAN: KEYS is no role's (redis_roles.py)
        return [json.loads(raw) for raw in client.mget(beats or ["-"]) if raw]

    def worker_pids(self) -> set[int]:
        return {int(str(beat["pid"])) for beat in self.heartbeats()}

    def stop(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in self.processes:
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            with contextlib.suppress(ProcessLookupError, PermissionError):  # a killed gateway's check pool
                os.killpg(process.pid, signal.SIGKILL)


def make_stack(
    tmp: Path,
    model_dir: Path,
    *,
    redis_config: str = "",
    cache_config: str | None = None,
    password: str | None = "stack-redis-password",
    **settings: str,
) -> Stack:
    """A stack on a fresh queue Redis (more redis-server options in `redis_config`, e.g. "--maxmemory 64mb"),
    and on a cache Redis of its own when `cache_config` is given; with `password` (the default), both require
    it and gateway and workers read it from a file, as in docker-compose."""
    return _make_stack(tmp, model_dir, redis_config, cache_config, password, False, settings)


def make_role_stack(tmp: Path, model_dir: Path, *, cache_config: str, **settings: str) -> Stack:
    """A stack whose two Redis have the users of precond/jobs/redis_roles.py, as in docker-compose: gateway and
    workers each connect to each Redis as their own user (the stack's `client()` as the gateway's)."""
    return _make_stack(tmp, model_dir, "", cache_config, None, True, settings)


def _make_stack(tmp: Path, model_dir: Path, redis_config: str, cache_config: str | None, password: str | None,
                roles: bool, settings: dict[str, str]) -> Stack:
    queue_users = RoleUsers(tmp, "queue") if roles else None
    server = RedisServer(tmp, password=password, config=tuple(redis_config.split()))
    if queue_users is not None:
        server = queue_users.server(server)
    server.start()
    cache = None
    cache_users = RoleUsers(tmp, "cache") if roles and cache_config is not None else None
    if cache_config is not None:
        cache = RedisServer(tmp, password=password, config=tuple(cache_config.split()))
        if cache_users is not None:
            cache = cache_users.server(cache)
        cache.start()
    redis_env = {"REDIS_URL": server.url}
    if cache is not None:
        redis_env["PRECOND_CACHE_REDIS_URL"] = cache.url
    if password is not None:
        secret_file = tmp / "redis-password"
        secret_file.write_text(password + "\n")
        redis_env["PRECOND_REDIS_PASSWORD_FILE"] = str(secret_file)
    env = {
        **os.environ,
        **redis_env,
        "MODEL_PATH": str(model_dir),
        "MODEL_THREADS": "1",
        "OMP_NUM_THREADS": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "SANDBOX_WORKERS": "2",
        # the slow jobs of these tests are legal programs: generous limits keep a busy machine from
        # turning them into limit errors (the limits themselves are tested in tests/sandbox)
        "SANDBOX_TIMEOUT_S": "60",
        "SANDBOX_CPU_S": "60",
        "PRECOND_HEARTBEAT_S": "0.5",
        "PRECOND_WORKER_POLL_S": "0.05",
        "PRECOND_WAIT_POLL_S": "0.02",
        "PRECOND_DRAIN_S": "1",
        "PRECOND_MAX_BODY_BYTES": "65536",
        "PYTHONPATH": str(ROOT),
        "PRECOND_SECRET": "stack-secret-for-tests",
        # checks are jobs, as the tests of the queue, the worker, the cache and the sandbox want them; a test of
        # the gateway's own judgement of a check turns it back on
        "PRECOND_INTERPRET_CHECKS": "false",
        **settings,
    }
    role_env = {} if queue_users is None else {
        kind: {**queue_users.settings(kind, server, "REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE"),
               **(cache_users.settings(kind, cache, "PRECOND_CACHE_REDIS_URL", "PRECOND_CACHE_REDIS_PASSWORD_FILE")
                  if cache is not None and cache_users is not None else {})}
        for kind in ("gateway", "worker")}
    return Stack(server, env, tmp, cache_redis=cache, roles=role_env)


class RoleUsers:
    """One Redis's users (precond/jobs/redis_roles.py), each with a fresh password in a file under `tmp`."""

    def __init__(self, tmp: Path, name: str) -> None:
        self.name = name
        self.passwords = {role: secrets.token_hex(16) for role in ROLES[name]}
        self.files = {role: tmp / password_file(name, role) for role in ROLES[name]}
        for role, path in self.files.items():
            path.write_text(self.passwords[role] + "\n")

    def server(self, server: RedisServer) -> RedisServer:
        """`server` with these users (and the gateway's for its own `client()`)."""
        return replace(server, user="gateway", password=self.passwords["gateway"],
                       acl="\n".join(acl_lines(self.name, self.passwords)) + "\n")

    def settings(self, kind: str, server: RedisServer, url: str, password: str) -> dict[str, str]:
        """The settings that make a process of `kind` connect to `server` as its own user."""
        return {url: f"redis://{kind}@127.0.0.1:{server.port}/0", password: str(self.files[kind])}


@contextmanager
def serving(stack: Stack, workers: int = 0) -> Iterator[Stack]:
    """The gateway (and `workers` workers) up for the block; everything the stack started is stopped after."""
    try:
        stack.start_gateway()
        for _ in range(workers):
            stack.start_worker()
        yield stack
    finally:
        stack.stop()
        stack.redis.stop()
        if stack.cache_redis is not None:
            stack.cache_redis.stop()
