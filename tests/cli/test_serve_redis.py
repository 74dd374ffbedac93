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


def _supervisor(tmp_path: Path, ports: tuple[int, int]) -> Supervisor:
    return Supervisor(
        WorkerSettings(), "127.0.0.1", free_port(), 1, tmp_path / "redis",
        redis_maxmemory="8mb", cache_maxmemory="4mb", redis_ports=ports,
    )


def test_serve_starts_two_closed_bounded_redis(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("REDIS_URL", "PRECOND_REDIS_URL", "PRECOND_CACHE_REDIS_URL", "PRECOND_REDIS_PASSWORD_FILE"):
        monkeypatch.delenv(name, raising=False)
    ports = (free_port(), free_port())
    supervisor = _supervisor(tmp_path, ports)
    queue_url, cache_url = supervisor.env["REDIS_URL"], supervisor.env["PRECOND_CACHE_REDIS_URL"]
    passwords = []
    for url, port in zip((queue_url, cache_url), ports, strict=True):
        match = re.fullmatch(rf"redis://:([0-9a-f]{{64}})@127\.0\.0\.1:{port}/0", url)
        assert match, url
        passwords.append(match.group(1))
    assert passwords[0] != passwords[1]
    again = _supervisor(tmp_path, ports)
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


def test_serve_refuses_an_open_redis_it_did_not_start_unless_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Redis without a password already on the port: the sets would go there, open to anyone; never silently."""
    _clear_redis_settings(monkeypatch)
    foreign = RedisServer(tmp_path)
    foreign.start()
    try:
        with pytest.raises(SystemExit) as refused:
            _supervisor(tmp_path, (foreign.port, free_port()))
        assert "without a password answers at 127.0.0.1:" in str(refused.value.code)
        assert "--redis-url" in str(refused.value.code)
        named = Supervisor(WorkerSettings(redis_url=foreign.url), "127.0.0.1", free_port(), 1, tmp_path / "r",
                           redis_ports=(foreign.port, free_port()))
        assert named.env["REDIS_URL"] == foreign.url and not named.redis  # told to: used, nothing started
        assert named.redis_used == (f"precond: Redis: queue redis://127.0.0.1:{foreign.port}/0 (WITHOUT a "
                                    "password) from REDIS_URL (also the cache)")
    finally:
        foreign.stop()


def test_serve_says_which_redis_it_starts_without_its_password(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _clear_redis_settings(monkeypatch)
    ports = (free_port(), free_port())
    supervisor = _supervisor(tmp_path, ports)
    line = supervisor.redis_used
    assert line.startswith("precond: Redis: started here, 127.0.0.1 only, with a random password per start")
    assert f"queue on port {ports[0]}" in line and f"result cache on port {ports[1]}" in line
    assert all(server.password not in line for server in supervisor.redis)
