"""`precond serve`'s private Redis: a queue Redis and a cache Redis, 127.0.0.1 only, with a fresh random
password per start that its children get through REDIS_URL and PRECOND_CACHE_REDIS_URL."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import redis

from precond.cli.supervisor import Supervisor
from precond.stack.local import RedisServer, free_port
from precond.worker.settings import WorkerSettings

pytestmark = pytest.mark.stack


def _supervisor(tmp_path: Path, port: int | None = None) -> Supervisor:
    return Supervisor(
        WorkerSettings(), "127.0.0.1", free_port(), 1, tmp_path / "redis",
        redis_maxmemory="8mb", cache_maxmemory="4mb", redis_port=port,
    )


def _ports(supervisor: Supervisor) -> tuple[int, int]:
    queue, cache = (server.port for server in supervisor.redis)
    return queue, cache


def test_serve_starts_two_closed_bounded_redis(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("REDIS_URL", "PRECOND_REDIS_URL", "PRECOND_CACHE_REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE"):
        monkeypatch.delenv(name, raising=False)
    supervisor = _supervisor(tmp_path)
    ports = _ports(supervisor)
    queue_url, cache_url = supervisor.env["REDIS_URL"], supervisor.env["PRECOND_CACHE_REDIS_URL"]
    passwords = []
    for url, port in zip((queue_url, cache_url), ports, strict=True):
        match = re.fullmatch(rf"redis://:([0-9a-f]{{64}})@127\.0\.0\.1:{port}/0", url)
        assert match, url
        passwords.append(match.group(1))
    assert passwords[0] != passwords[1]
    again = _supervisor(tmp_path)
    assert again.env["REDIS_URL"] != queue_url, "the password is drawn anew at each start"

    servers = [child for child in supervisor.children if child.name.startswith("redis")]
    assert [child.name for child in servers] == ["redis", "redis-cache"]
    try:
        for child in servers:
            child.start(supervisor.env)
        for server in supervisor.redis:
            supervisor.wait_for_redis(server)
        for child, password in zip(servers, passwords, strict=True):
            assert child.process is not None
            cmdline = Path(f"/proc/{child.process.pid}/cmdline").read_bytes()
            assert password.encode() not in cmdline, "the password must not show in a process listing"
        for port in ports:
            with pytest.raises(redis.AuthenticationError):
                redis.Redis(port=port, socket_timeout=2).ping()
        queue = redis.Redis.from_url(queue_url, socket_timeout=2)
        cache = redis.Redis.from_url(cache_url, socket_timeout=2)
        assert queue.config_get("maxmemory-policy") == {"maxmemory-policy": "noeviction"}
        assert queue.config_get("maxmemory") == {"maxmemory": str(8 * 1024 * 1024)}
        assert queue.config_get("appendonly") == {"appendonly": "yes"}
        assert cache.config_get("maxmemory-policy") == {"maxmemory-policy": "allkeys-lru"}
        assert cache.config_get("maxmemory") == {"maxmemory": str(4 * 1024 * 1024)}
        assert cache.config_get("appendonly") == {"appendonly": "no"} and cache.config_get("save") == {"save": ""}
        for client in (queue, cache):
            assert client.config_get("bind") == {"bind": "127.0.0.1"}
    finally:
        for child in servers:
            if child.process is not None:
                child.process.terminate()
                child.process.wait(10)


def _clear_redis_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("REDIS_URL", "PRECOND_REDIS_URL", "PRECOND_CACHE_REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE"):
        monkeypatch.delenv(name, raising=False)


def test_serve_starts_its_own_beside_an_open_redis_and_never_offers_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A passwordless Redis of the machine's (Debian's redis-server on 6379) is no reason not to start: the
    private pair takes free ports. Only a port the user names and someone else holds is refused, and the
    refusal points at another port, never at the open Redis."""
    _clear_redis_settings(monkeypatch)
    foreign = RedisServer(tmp_path)
    foreign.start()
    try:
        beside = _supervisor(tmp_path)
        assert foreign.port not in _ports(beside) and len(set(_ports(beside))) == 2
        for taken in (foreign.port, foreign.port - 1):  # the queue's port, or the cache's (the next one)
            with pytest.raises(SystemExit) as refused:
                _supervisor(tmp_path, taken)
            message = str(refused.value.code)
            assert f"port {foreign.port} of 127.0.0.1" in message and "--redis-port" in message, message
            assert "--redis-url" not in message and "REDIS_URL" not in message, "never offer the open Redis"
        named = Supervisor(WorkerSettings(redis_url=foreign.url), "127.0.0.1", free_port(), 1, tmp_path / "r")
        assert named.env["REDIS_URL"] == foreign.url and not named.redis  # told to: used, nothing started
        assert named.redis_used == (f"precond: Redis: queue redis://127.0.0.1:{foreign.port}/0 (WITHOUT a "
                                    "password) from REDIS_URL (also the cache)")
    finally:
        foreign.stop()


def test_serve_says_which_redis_it_starts_without_its_password(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _clear_redis_settings(monkeypatch)
    port = free_port()
    supervisor = _supervisor(tmp_path, port)
    assert _ports(supervisor) == (port, port + 1)
    line = supervisor.redis_used
    assert line.startswith("precond: Redis: started here, 127.0.0.1 only, with a random password per start")
    assert f"queue on port {port}" in line and f"result cache on port {port + 1}" in line
    assert all(server.password not in line for server in supervisor.redis)
    assert supervisor.redis_short == (f"its own password-protected Redis on 127.0.0.1:{port} (queue) and "
                                      f":{port + 1} (cache)")
