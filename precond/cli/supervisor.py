"""`precond serve`: gateway, workers and (if needed) private redis-servers as one process tree.

For a single machine without an orchestrator. Children are restarted when they die, and all of them are
stopped (SIGTERM, then SIGKILL after the drain period) when the supervisor gets SIGINT or SIGTERM. Only the
standard library is used (and the gateway's command line), so starting the tree loads no engine.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import secrets
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
from urllib.parse import urlsplit

from precond.gateway.server import gateway_args
from precond.jobs.lifetime import die_with_parent
from precond.worker.settings import WorkerSettings

log = logging.getLogger("precond.serve")
LOCAL_HOST = "127.0.0.1"


@dataclass
class Child:
    name: str
    argv: list[str]
    stdin: bytes | None = None
    """Written to the child's stdin at each start, then closed (a redis-server's config: its password)."""
    process: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    started: float = field(default=0.0)

    def start(self, env: dict[str, str]) -> None:
        log.info("starting %s: %s", self.name, " ".join(self.argv))
        self.process = subprocess.Popen(  # its own process group: what it starts is stopped with it
            self.argv, env=env, stdin=None if self.stdin is None else subprocess.PIPE, start_new_session=True,
            preexec_fn=functools.partial(die_with_parent, os.getpid()),  # and it ends with `precond serve`
        )
        if self.stdin is not None and self.process.stdin is not None:
            self.process.stdin.write(self.stdin)
            self.process.stdin.close()
        self.started = time.monotonic()

    def exited(self) -> int | None:
        return None if self.process is None else self.process.poll()

    def kill_leftovers(self) -> None:
        """SIGKILL what is left of the child's process group once it is gone: a gateway killed before it could
        stop its check pool leaves that pool's processes and their resource tracker behind, orphaned."""
        if self.process is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.process.pid, signal.SIGKILL)


def answers(host: str, port: int, password: str) -> bool:
    """Our Redis answers PING at host:port after AUTH with its password (a passwordless one that took the port
    first refuses the AUTH, and so is never taken for ours)."""
    try:
        with socket.create_connection((host, port), timeout=0.5) as conn:
            conn.sendall(b"AUTH " + password.encode() + b"\r\nPING\r\n")
            reply = b""
            while b"PONG" not in reply and not reply.startswith(b"-") and len(reply) < 256:
                chunk = conn.recv(64)
                if not chunk:
                    break
                reply += chunk
    except OSError:
        return False
    return reply.startswith(b"+OK") and b"+PONG" in reply


def listening(host: str, port: int) -> bool:
    """Something accepts connections at host:port (a Redis of the machine's, or anything else)."""
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def free_ports(count: int) -> tuple[int, ...]:
    """Ports the OS has just handed out as free on 127.0.0.1: the private Redis need none in particular, and a
    fixed one (6379) is where a distribution's own redis-server usually already runs."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind((LOCAL_HOST, 0))
        return tuple(sock.getsockname()[1] for sock in sockets)
    finally:
        for sock in sockets:
            sock.close()


def private_ports(queue_port: int | None) -> tuple[int, int]:
    """The private queue and cache Redis ports: `--redis-port` and the next one, else two free ones. A named port
    that something already holds is refused with what to do (never "use that one": it is not ours)."""
    if queue_port is None:
        queue, cache = free_ports(2)
        return queue, cache
    for port, role in ((queue_port, "queue"), (queue_port + 1, "cache")):
        if listening(LOCAL_HOST, port):
            raise SystemExit(
                f"--redis-port {queue_port}: port {port} of {LOCAL_HOST} (for the private {role} Redis) is taken "
                "by a process precond serve did not start; name another port with --redis-port (the cache Redis "
                "takes the next one), or leave --redis-port out and two free ports are chosen")
    return queue_port, queue_port + 1


def is_ready(url: str) -> bool:
    """The gateway's /ready answers 200: Redis up and a worker with its model loaded."""
    try:
        with urllib.request.urlopen(url, timeout=0.5) as answer:
            return bool(answer.status == 200)
    except (OSError, ValueError):
        return False


def _shown(url: str) -> str:
    """A Redis URL as logged: the password replaced by `***`, and whether there is one."""
    parts = urlsplit(url)
    host = parts.netloc.rpartition("@")[2]
    secret = "with a password" if parts.password else "WITHOUT a password"
    return f"{parts.scheme}://{host}{parts.path} ({secret})"


def redis_description(settings: WorkerSettings, private: tuple[PrivateRedis, ...], data_dir: Path) -> str:
    """Which Redis the processes use, in one line for the operator (never the password)."""
    if private:
        queue, cache = private
        return (f"precond: Redis: started here, 127.0.0.1 only, with a random password per start: queue on port "
                f"{queue.port} (append-only file in {data_dir}), result cache on port {cache.port}"
                + ("" if settings.cache_redis_url is None else f"; cache: {_shown(settings.cache_redis_dsn)}"))
    own_cache = f"; cache: {_shown(settings.cache_redis_dsn)}" if settings.cache_redis_url else " (also the cache)"
    return f"precond: Redis: queue {_shown(settings.redis_dsn)} from REDIS_URL{own_cache}"


def redis_in_short(settings: WorkerSettings, private: tuple[PrivateRedis, ...]) -> str:
    """Which Redis, for the ready line (the one line a user greps for)."""
    if private:
        queue, cache = private
        return f"its own password-protected Redis on {LOCAL_HOST}:{queue.port} (queue) and :{cache.port} (cache)"
    return f"Redis {_shown(settings.redis_dsn)} from REDIS_URL"


@dataclass(frozen=True)
class PrivateRedis:
    """One of the two redis-servers `precond serve` starts when REDIS_URL is unset (on free ports, or
    `--redis-port` and the next one):

    * the queue Redis (jobs, results, progress, heartbeats): append-only file in `data_dir`, and
      `maxmemory` with `noeviction`, so a full Redis refuses new work (503) instead of dropping accepted work;
    * the cache Redis (result-cache entries only): no persistence, `maxmemory` with `allkeys-lru`.

    Both bind 127.0.0.1 and require a password drawn at random for each start of `precond serve`; its
    children get it through REDIS_URL and PRECOND_CACHE_REDIS_URL. The password reaches redis-server on its
    stdin (as configuration), so it never shows in a process listing.
    """

    name: str
    port: int
    maxmemory: str
    policy: str
    data_dir: Path | None
    password: str = field(default_factory=lambda: secrets.token_hex(32), repr=False)

    @property
    def url(self) -> str:
        return f"redis://:{self.password}@{LOCAL_HOST}:{self.port}/0"

    def child(self) -> Child:
        binary = shutil.which("redis-server")
        if binary is None:
            raise SystemExit(
                "REDIS_URL is unset and redis-server is not installed: install it (apt-get install redis-server), "
                "or name a Redis with --redis-url"
            )
        argv = [binary, "-", "--bind", LOCAL_HOST, "--port", str(self.port), "--protected-mode", "yes",
                "--maxmemory", self.maxmemory, "--maxmemory-policy", self.policy]
        if self.data_dir is None:
            argv += ["--save", "", "--appendonly", "no"]
        else:
            self.data_dir.mkdir(parents=True, exist_ok=True)
            argv += ["--dir", str(self.data_dir), "--appendonly", "yes"]
        return Child(self.name, argv, stdin=f"requirepass {self.password}\n".encode())


def private_redis(
    data_dir: Path, ports: tuple[int, int], queue_maxmemory: str, cache_maxmemory: str
) -> tuple[PrivateRedis, PrivateRedis]:
    """The queue Redis and the cache Redis of `precond serve` (see PrivateRedis)."""
    return (
        PrivateRedis("redis", ports[0], queue_maxmemory, "noeviction", data_dir),
        PrivateRedis("redis-cache", ports[1], cache_maxmemory, "allkeys-lru", None),
    )


class Supervisor:
    def __init__(
        self,
        settings: WorkerSettings,
        host: str,
        port: int,
        workers: int,
        data_dir: Path,
        gateway_processes: int = 1,
        redis_maxmemory: str = "512mb",
        cache_maxmemory: str = "256mb",
        redis_port: int | None = None,
        ready_note: str = "",
        env: dict[str, str] | None = None,
    ) -> None:
        """`ready_note`: what the ready line adds (what an open service's one tenant may do); `env`: settings
        for every process started here, over this process's environment."""
        self.settings = settings
        self.env = {**os.environ, **(env or {})}
        self.ready_note = ready_note
        self.children: list[Child] = []
        self.redis: tuple[PrivateRedis, ...] = ()
        if settings.redis_url is None:
            self.redis = private_redis(data_dir, private_ports(redis_port), redis_maxmemory, cache_maxmemory)
            queue, cache = self.redis
            self.children += [queue.child(), cache.child()]
            self.env["REDIS_URL"] = queue.url
            self.env.pop("PRECOND_REDIS_URL", None)
            if settings.cache_redis_url is None:  # an operator's own cache Redis is kept, else ours is used
                self.env["PRECOND_CACHE_REDIS_URL"] = cache.url
        else:  # an operator's Redis, named by REDIS_URL or --redis-url
            self.env["REDIS_URL"] = settings.redis_url
            self.env.pop("PRECOND_REDIS_URL", None)
        self.redis_used = redis_description(settings, self.redis, data_dir)
        self.redis_short = redis_in_short(settings, self.redis)
        if settings.secret is None and settings.secret_file is None:  # one secret for the processes started here
            self.env["PRECOND_SECRET"] = secrets.token_urlsafe(32)
        gateway = [sys.executable, "-m", "uvicorn", *gateway_args(gateway_processes)]
        self.children.append(Child("gateway", [*gateway, "--host", host, "--port", str(port)]))
        worker = [sys.executable, "-m", "precond.worker.runner"]
        self.children += [Child(f"worker-{i}", worker) for i in range(workers)]
        self.stopping = False
        self.ready_url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}/ready"
        self.announced = False

    def run(self) -> int:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._stop)
        print(self.redis_used, file=sys.stderr, flush=True)
        redis = [c for c in self.children if c.name.startswith("redis")]
        for child in redis:
            child.start(self.env)
        for server in self.redis:
            self.wait_for_redis(server)
        for child in self.children:
            if child not in redis:
                child.start(self.env)
        while not self.stopping:
            for child in self.children:
                self._restart_if_dead(child)
            if not self.announced and is_ready(self.ready_url):
                self.announced = True
                print(f"precond: ready at {self.ready_url.removesuffix('/ready')} (GET /ready answers 200), "
                      f"using {self.redis_short}{self.ready_note}", flush=True)
            time.sleep(0.5)
        return self._shutdown()

    @staticmethod
    def wait_for_redis(server: PrivateRedis, timeout_s: float = 10) -> None:
        deadline = time.monotonic() + timeout_s
        while not answers(LOCAL_HOST, server.port, server.password):
            if time.monotonic() > deadline:
                raise SystemExit(f"the private {server.name}-server did not come up")
            time.sleep(0.1)

    def _restart_if_dead(self, child: Child) -> None:
        code = child.exited()
        if code is None or self.stopping:
            return
        backoff = min(30.0, 2.0**child.restarts) if time.monotonic() - child.started < 60 else 1.0
        log.warning("%s exited with %s; restarting in %.0fs", child.name, code, backoff)
        child.kill_leftovers()
        time.sleep(backoff)
        child.restarts += 1
        child.start(self.env)

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        self.stopping = True

    def _shutdown(self) -> int:
        # Redis goes last: draining workers still hand their jobs back through it.
        for group in (
            [c for c in self.children if not c.name.startswith("redis")],
            [c for c in self.children if c.name.startswith("redis")],
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
                        child.process.wait()
                    child.kill_leftovers()
        return 0
