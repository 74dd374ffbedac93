"""The Redis users are what precond/jobs/redis_roles.py claims, on real redis-servers started as compose and the
manifests start them (the ACL lines that docker/keys.py writes, read on standard input): KEDA's user runs KEDA's
own length script and nothing else, the cache users reach cache entries and nothing else, a credential of one
Redis opens nothing on the other, and a connection that names no user can do nothing."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import redis
from redis.exceptions import AuthenticationError, NoPermissionError, ResponseError

from precond.jobs.queue.keys import CHECK_QUEUE, JOB_PREFIX, cache_key
from precond.jobs.redis_roles import ROLES, acl_file, password_file
from precond.stack.local import free_port, wait_until

ROOT = Path(__file__).resolve().parents[2]
KEDA_SCRIPT = """
    local listName = KEYS[1]
    local listType = redis.call('type', listName).ok
    local cmd = {zset = 'zcard', set = 'scard', list = 'llen', hash = 'hlen', none = 'llen'}
    return redis.call(cmd[listType], listName)
"""
"""KEDA's Redis scaler's query (pkg/scalers/redis_scaler.go), the one EVAL its user exists for."""
REFUSED = "(?i)no permissions|can't run this command"
"""How Redis refuses a command the user may not run: NOPERM, directly or from a script."""


class Servers:
    """Both Redis, each started with its ACL lines on standard input, and the users' passwords."""

    def __init__(self, secrets: Path) -> None:
        self.secrets = secrets
        self.ports: dict[str, int] = {}
        self.processes: list[subprocess.Popen[bytes]] = []

    def start(self, server: str) -> None:
        port = free_port()
        process = subprocess.Popen(["/usr/bin/redis-server", "-", "--port", str(port), "--bind", "127.0.0.1",
                                    "--save", "", "--appendonly", "no"], stdin=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL)
        assert process.stdin is not None
        process.stdin.write((self.secrets / acl_file(server)).read_bytes())
        process.stdin.close()
        self.processes.append(process)
        self.ports[server] = port
        wait_until(lambda: self.client(server, "probe").ping(), 10, f"the {server} Redis")

    def password(self, server: str, role: str) -> str:
        return (self.secrets / password_file(server, role)).read_text().strip()

    def client(self, server: str, role: str, on: str | None = None) -> redis.Redis[bytes]:
        """A client of `role`'s user of `server`, connecting to the Redis `on` (`server` unless named)."""
        return redis.Redis(port=self.ports[on or server], username=role, password=self.password(server, role),
                           socket_timeout=5)


@pytest.fixture(scope="module")
def servers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Servers]:
    secrets = tmp_path_factory.mktemp("secrets")
    subprocess.run([sys.executable, str(ROOT / "docker" / "keys.py"), "--redis", str(secrets)], check=True,
                   capture_output=True)
    running = Servers(secrets)
    try:
        running.start("queue")
        running.start("cache")
        yield running
    finally:
        for process in running.processes:
            process.terminate()
            process.wait(10)


def test_keda_reads_a_queues_length_and_nothing_else(servers: Servers) -> None:
    gateway, keda = servers.client("queue", "gateway"), servers.client("queue", "keda")
    gateway.zadd(CHECK_QUEUE, {"a": 1, "b": 2})
    gateway.set(JOB_PREFIX + "a", b"a job's record")
    assert keda.eval(KEDA_SCRIPT, 1, CHECK_QUEUE) == 2  # type: ignore[no-untyped-call]
    assert keda.zcard(CHECK_QUEUE) == 2
    refused: list[Callable[[], object]] = [
        lambda: keda.get(JOB_PREFIX + "a"),
        lambda: keda.zrange(CHECK_QUEUE, 0, -1),  # the queue's job ids
        lambda: keda.zadd(CHECK_QUEUE, {"forged": 0}),
        lambda: keda.eval("return redis.call('GET', KEYS[1])", 1, CHECK_QUEUE),  # type: ignore[no-untyped-call]
        lambda: keda.eval("return redis.call('ZADD', KEYS[1], 0, 'x')", 1, CHECK_QUEUE),  # type: ignore[no-untyped-call]
        lambda: keda.eval(KEDA_SCRIPT, 1, JOB_PREFIX + "a"),  # type: ignore[no-untyped-call]
        lambda: keda.eval("return redis.call('GET', 'arq:job:a')", 0),  # type: ignore[no-untyped-call]
        lambda: keda.publish("precond:wake:" + CHECK_QUEUE, b"1"),
        lambda: keda.config_get("*"),
        lambda: keda.keys("*"),
    ]
    for attempt in refused:
        with pytest.raises((NoPermissionError, ResponseError), match=REFUSED):
            attempt()
    assert gateway.zcard(CHECK_QUEUE) == 2 and gateway.get(JOB_PREFIX + "a") == b"a job's record"


@pytest.mark.parametrize("role", sorted(ROLES["cache"].keys() - {"probe"}))
def test_a_cache_user_reaches_cache_entries_only(servers: Servers, role: str) -> None:
    cache = servers.client("cache", role)
    assert cache.set(cache_key("j"), b"entry") and cache.get(cache_key("j")) == b"entry"
    assert cache.delete(cache_key("j")) == 1
    for attempt in (lambda: cache.zcard(CHECK_QUEUE), lambda: cache.get(JOB_PREFIX + "a"),
                    lambda: cache.eval("return 1", 0),  # type: ignore[no-untyped-call]
                    lambda: cache.publish("precond:notice:x", b"1"), lambda: cache.flushall()):
        with pytest.raises((NoPermissionError, ResponseError), match=REFUSED):
            attempt()
    with pytest.raises(AuthenticationError):  # its credential opens nothing on the queue Redis
        servers.client("cache", role, on="queue").ping()


@pytest.mark.parametrize("role", ["gateway", "worker"])
def test_the_services_users_run_the_queue_but_never_administer_it(servers: Servers, role: str) -> None:
    user = servers.client("queue", role)
    script = "return redis.call('ZCARD', KEYS[1])"
    assert user.eval(script, 1, CHECK_QUEUE) >= 0  # type: ignore[no-untyped-call]
    for attempt in (lambda: user.config_set("maxmemory", "1"), lambda: user.flushall(), lambda: user.keys("*"),
                    lambda: user.client_list()):
        with pytest.raises((NoPermissionError, ResponseError), match=REFUSED):
            attempt()
    with pytest.raises(AuthenticationError):
        servers.client("queue", role, on="cache").ping()


def test_a_connection_without_a_user_can_do_nothing(servers: Servers) -> None:
    for server in ("queue", "cache"):
        anonymous = redis.Redis(port=servers.ports[server], socket_timeout=5)
        with pytest.raises(AuthenticationError):
            anonymous.ping()
        probe = servers.client(server, "probe")
        assert probe.ping()
        with pytest.raises(NoPermissionError):
            probe.get(cache_key("j"))
