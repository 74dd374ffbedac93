"""`precond serve`: gateway, workers and (if needed) a private redis-server as one process tree.

For a single machine without an orchestrator. Children are restarted when they die, and all of them are
stopped (SIGTERM, then SIGKILL after the drain period) when the supervisor gets SIGINT or SIGTERM. Only the
standard library is used, so it adds nothing to what the gateway imports.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

from jobs.settings import WorkerSettings

log = logging.getLogger("precond.serve")
LOCAL_REDIS = ("127.0.0.1", 6379)


@dataclass
class Child:
    name: str
    argv: list[str]
    process: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    started: float = field(default=0.0)

    def start(self, env: dict[str, str]) -> None:
        log.info("starting %s: %s", self.name, " ".join(self.argv))
        self.process = subprocess.Popen(self.argv, env=env)
        self.started = time.monotonic()

    def exited(self) -> int | None:
        return None if self.process is None else self.process.poll()


def answers(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5) as conn:
            conn.sendall(b"PING\r\n")
            return conn.recv(16).startswith(b"+PONG")
    except OSError:
        return False


def is_ready(url: str) -> bool:
    """The gateway's /ready answers 200: Redis up and a worker with its model loaded."""
    try:
        with urllib.request.urlopen(url, timeout=0.5) as answer:
            return bool(answer.status == 200)
    except (OSError, ValueError):
        return False


def redis_child(data_dir: Path) -> Child:
    binary = shutil.which("redis-server")
    if binary is None:
        raise SystemExit(
            "REDIS_URL is unset, nothing answers at 127.0.0.1:6379, and redis-server is not installed"
        )
    data_dir.mkdir(parents=True, exist_ok=True)
    argv = [
        binary,
        "--bind",
        "127.0.0.1",
        "--port",
        str(LOCAL_REDIS[1]),
        "--dir",
        str(data_dir),
        "--appendonly",
        "yes",
    ]
    return Child("redis", argv)


class Supervisor:
    def __init__(self, settings: WorkerSettings, host: str, port: int, workers: int, data_dir: Path) -> None:
        self.settings = settings
        self.env = dict(os.environ)
        self.children: list[Child] = []
        if settings.redis_url is None and not answers(*LOCAL_REDIS):
            self.children.append(redis_child(data_dir))
        self.env["REDIS_URL"] = settings.redis_dsn
        gateway = [sys.executable, "-m", "uvicorn", "service.app:create_app", "--factory"]
        self.children.append(Child("gateway", [*gateway, "--host", host, "--port", str(port)]))
        worker = [sys.executable, "-m", "worker.runner"]
        self.children += [Child(f"worker-{i}", worker) for i in range(workers)]
        self.stopping = False
        self.ready_url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}/ready"
        self.announced = False

    def run(self) -> int:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._stop)
        for child in self.children:
            child.start(self.env)
            if child.name == "redis":
                self._wait_for_redis()
        while not self.stopping:
            for child in self.children:
                self._restart_if_dead(child)
            if not self.announced and is_ready(self.ready_url):
                self.announced = True
                print(f"precond: ready at {self.ready_url.removesuffix('/ready')} (GET /ready answers 200)", flush=True)
            time.sleep(0.5)
        return self._shutdown()

    def _wait_for_redis(self, timeout_s: float = 10) -> None:
        deadline = time.monotonic() + timeout_s
        while not answers(*LOCAL_REDIS):
            if time.monotonic() > deadline:
                raise SystemExit("the private redis-server did not come up")
            time.sleep(0.1)

    def _restart_if_dead(self, child: Child) -> None:
        code = child.exited()
        if code is None or self.stopping:
            return
        backoff = min(30.0, 2.0**child.restarts) if time.monotonic() - child.started < 60 else 1.0
        log.warning("%s exited with %s; restarting in %.0fs", child.name, code, backoff)
        time.sleep(backoff)
        child.restarts += 1
        child.start(self.env)

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        self.stopping = True

    def _shutdown(self) -> int:
        # Redis goes last: draining workers still hand their jobs back through it.
        for group in (
            [c for c in self.children if c.name != "redis"],
            [c for c in self.children if c.name == "redis"],
        ):
            for child in group:
                if child.process and child.exited() is None:
                    child.process.terminate()
            for child in group:
                if child.process:
                    try:
                        child.process.wait(timeout=self.settings.drain_s + 5)
                    except subprocess.TimeoutExpired:
                        child.process.kill()
        return 0
