"""Real Redis, real worker processes and a real uvicorn gateway, each on free ports in temp dirs.

Every piece runs as its own process so tests can stop Redis, SIGKILL a worker or restart things the way an
operator would. The stub engine (tests/service/stub_engine.py) keeps workers free of torch and the sandbox.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import redis

ROOT = Path(__file__).resolve().parents[2]
SPEC = (
    "class USER:\n  def __init__(self):\n    self.informed = False\n"
    "  def INFORM(self, slot): self.informed = True\n"
    "class SYSTEM:\n  def __init__(self, user):\n    self.user = user\n  def REQUEST(self, slot): pass\n"
)
DEMO = "user = USER()\nsystem = SYSTEM(user)\nsystem.REQUEST('city')\nuser.INFORM('city')\n"


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

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def client(self) -> redis.Redis[bytes]:
        return redis.Redis(port=self.port, socket_timeout=2)

    def start(self) -> None:
        argv = [
            "/usr/bin/redis-server",
            "--port",
            str(self.port),
            "--bind",
            "127.0.0.1",
            "--dir",
            str(self.directory),
        ]
        self.process = subprocess.Popen(
            [*argv, "--save", "", "--appendonly", "no"], stdout=subprocess.DEVNULL
        )
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

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def http(self, timeout: float = 30) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=timeout)

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        log = (self.logs / f"{name}-{len(self.processes)}.log").open("wb")
        process = subprocess.Popen(argv, env=self.env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        self.processes.append(process)
        return process

    def start_gateway(self) -> None:
        argv = [
            sys.executable,
            "-m",
            "uvicorn",
            "service.app:create_app",
            "--factory",
            "--port",
            str(self.port),
        ]
        self._spawn("gateway", [*argv, "--log-level", "warning"])
        wait_until(lambda: self.http().get("/health").status_code == 200, 20, "gateway")

    def start_worker(self) -> subprocess.Popen[bytes]:
        before = self.worker_pids()
        process = self._spawn("worker", [sys.executable, "-m", "worker.runner"])
        wait_until(lambda: self.worker_pids() - before, 20, "worker heartbeat")
        return process

    def heartbeats(self) -> list[dict[str, object]]:
        import json

        client = self.redis.client()
        return [json.loads(raw) for raw in client.mget(client.keys("precond:worker:*") or ["-"]) if raw]

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


def make_stack(tmp: Path, **settings: str) -> Stack:
    server = RedisServer(tmp)
    server.start()
    env = {
        **os.environ,
        "REDIS_URL": server.url,
        "PRECOND_ENGINE_FACTORY": "tests.service.stub_engine:build",
        "PRECOND_HEARTBEAT_S": "0.5",
        "PRECOND_WORKER_POLL_S": "0.05",
        "PRECOND_WAIT_POLL_S": "0.02",
        "PRECOND_DRAIN_S": "1",
        "PRECOND_MAX_BODY_BYTES": "65536",
        "PYTHONPATH": str(ROOT),
        **settings,
    }
    return Stack(server, env, tmp)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """One stack per test module: modules that break things (Redis, workers) do not disturb others."""
    stack = make_stack(
        tmp_path_factory.mktemp("stack"), PRECOND_QUEUE_MAX_JOBS="3", PRECOND_JOB_TIMEOUT_S="3"
    )
    try:
        stack.start_gateway()
        stack.start_worker()
        yield stack
    finally:
        stack.stop()
        stack.redis.stop()


@pytest.fixture()
def client(stack: Stack) -> Iterator[httpx.Client]:
    with stack.http() as http:
        yield http


def infer_body(spec: str = SPEC, **options: object) -> dict[str, object]:
    return {"spec": spec, "demonstrations": [DEMO], "options": {"generators": ["enumerate"], **options}}
