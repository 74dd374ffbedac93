"""`/health`'s view of the workers against a real redis-server: a flood of polls costs Redis one heartbeat
scan a second, and the view still says what the heartbeats say."""

from __future__ import annotations

import asyncio

import pytest
from redis.asyncio import Redis

from precond.gateway.worker_view import UNCONFINED, UNKNOWN, WorkerView
from precond.jobs.queue.keys import worker_key
from precond.stack.local import RedisServer


def _beat(sandbox: str) -> str:
    return ('{"id": "w1", "host": "h", "pid": 1, "queues": ["q"], "model_loaded": true, '
            f'"sandbox": "{sandbox}"}}')


def _scans(server: RedisServer) -> int:
    return int(server.client().info("commandstats").get("cmdstat_scan", {}).get("calls", 0))


def test_many_polls_share_one_read_of_the_heartbeats(redis_server: RedisServer) -> None:
    key = worker_key("w1")

    async def run() -> tuple[list[str], str]:
        redis: Redis[bytes] = Redis.from_url(redis_server.url)
        await redis.set(key, _beat("confined"))
        view = WorkerView(redis, max_age_s=60)
        answers = await asyncio.gather(*(view.sandbox(2.0) for _ in range(200)))
        answers += [await view.sandbox(2.0) for _ in range(200)]
        await redis.set(key, _beat("unconfined"))
        stale = await view.sandbox(2.0)  # within max_age: what was read, not Redis's every change
        await redis.aclose()
        return answers, stale

    answers, stale = asyncio.run(run())
    assert set(answers) == {"confined"} and stale == "confined"
    assert _scans(redis_server) == 1


def test_an_unconfined_worker_is_a_code_named_only_in_the_log_and_redis_down_is_unknown(
    redis_server: RedisServer, caplog: pytest.LogCaptureFixture
) -> None:
    async def run() -> tuple[str, str]:
        redis: Redis[bytes] = Redis.from_url(redis_server.url)
        await redis.set(worker_key("w1"), _beat("unconfined"))
        named = await WorkerView(redis, max_age_s=60).sandbox(2.0)
        redis_server.stop()
        down = await WorkerView(redis, max_age_s=60).sandbox(2.0)
        return named, down

    named, down = asyncio.run(run())
    assert named == UNCONFINED  # anybody may read /health: which worker it is goes to the log only
    assert "UNCONFINED on w1" in caplog.text
    assert down == UNKNOWN
