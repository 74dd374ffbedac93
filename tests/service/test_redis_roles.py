"""Redis bounded and closed, on a real stack with the two Redis roles of docker-compose and `precond serve`:

* the queue Redis (jobs, results, progress, heartbeats) with `maxmemory` and `noeviction`: full, it refuses
  writes, the gateway answers 503 + Retry-After, and nothing it accepted is lost;
* the cache Redis (result-cache entries only) with a small `maxmemory` (2 MB) and `allkeys-lru`: flooding it
  evicts cache entries, never queued jobs or owed results;
* both require a password, which gateway and workers read from `PRECOND_REDIS_PASSWORD_FILE`;
* with a user per role (precond/jobs/redis_roles.py: the users of compose and the manifests), gateway and worker
  each serve as their own, on each Redis;
* every key the service writes expires or belongs to a short list of bounded keys;
* a cache entry no worker signed is never served.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from redis.asyncio import Redis as AsyncRedis

from precond.gateway.settings import GatewaySettings
from precond.jobs import cache
from precond.jobs.cache import ResultCache
from precond.jobs.queue import keys
from precond.jobs.settings import QueueSettings
from precond.stack.local import (
    DEMOS,
    SPEC,
    Stack,
    check_body,
    infer_body,
    make_role_stack,
    make_stack,
    serving,
    wait_until,
)
from precond_client.schemas import CheckRequest, CheckResponse

PASSWORD = "roles-test-redis-password"
QUEUE_MAXMEMORY = 64 * 1024 * 1024
CACHE_MAXMEMORY = 2 * 1024 * 1024
QUEUE_MAX_JOBS = 16
RETRY_AFTER_S = "3"

BOUNDED_KEYS = {
    **{queue: f"an arq queue: at most PRECOND_QUEUE_MAX_JOBS ({QUEUE_MAX_JOBS}) jobs" for queue in keys.QUEUES},
    keys.STATS_KEY: "the workers' counters: one field per kind × outcome and kind × engine phase",
    keys.RUNNING_KEY: "claims of running jobs: one per job a worker runs, removed at its end or by a beat",
    "arq:abort": "arq's abort marks: only for queued or running jobs, removed when the job ends or re-enqueues",
    keys.UNCLAIMED_KEY: "jobs started but not yet claimed: one field per queued job at most, dropped by the next "
    "beat once the job is claimed, handed back or gone",
}
"""The only keys without a TTL, and why each stays small (docs/service.md, "Redis: two roles, bounded and closed")."""


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    """The gateway on a queue Redis and a cache Redis of its own; tests start a worker when they need one."""
    stack = make_stack(
        tmp_path_factory.mktemp("roles"),
        tiny_model_dir,
        redis_config=f"--maxmemory {QUEUE_MAXMEMORY} --maxmemory-policy noeviction",
        cache_config=f"--maxmemory {CACHE_MAXMEMORY} --maxmemory-policy allkeys-lru",
        password=PASSWORD,
        PRECOND_QUEUE_MAX_JOBS=str(QUEUE_MAX_JOBS),
        PRECOND_RETRY_AFTER_S=RETRY_AFTER_S,
        PRECOND_WAIT_MAX_S="60",  # a `?wait=60` waits that long on a busy machine (a training, an inference)
    )
    with serving(stack):
        yield stack


@contextmanager
def worker(stack: Stack) -> Iterator[None]:
    process = stack.start_worker()
    try:
        yield
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(30)


def queue_redis(stack: Stack) -> redis.Redis[bytes]:
    return stack.redis.client()


def cache_redis(stack: Stack) -> redis.Redis[bytes]:
    assert stack.cache_redis is not None
    return stack.cache_redis.client()


def secret(stack: Stack) -> bytes:
    return stack.env["PRECOND_SECRET"].encode()


def forget_queued(stack: Stack, job_ids: list[str]) -> None:
    """Take this test's never-run jobs out of the queue, so the next test's worker does not run them."""
    client = queue_redis(stack)
    for job_id in job_ids:
        for queue in keys.QUEUES:
            client.zrem(queue, job_id)
        client.delete(f"arq:job:{job_id}")


def test_both_redis_require_the_password(stack: Stack) -> None:
    for server in (stack.redis, stack.cache_redis):
        assert server is not None
        with pytest.raises(redis.AuthenticationError):
            redis.Redis(port=server.port, socket_timeout=2).ping()
    assert "REDIS_URL" in stack.env and PASSWORD not in stack.env["REDIS_URL"]  # it comes from the file
    with httpx.Client(base_url=stack.base_url, timeout=30) as client:
        answer = client.post("/check-actions", json=check_body("system.REQUEST('city')"), params={"wait": 0})
    assert answer.status_code == 202  # accepted: the gateway authenticated to the queue Redis


@pytest.mark.stack
def test_gateway_and_worker_serve_as_their_own_redis_users(tmp_path: Path, tiny_model_dir: Path) -> None:
    roles = make_role_stack(tmp_path, tiny_model_dir, cache_config="--maxmemory 2mb --maxmemory-policy allkeys-lru")
    with serving(roles, workers=1), roles.http() as client:
        answer = client.post("/infer-preconditions", json=infer_body(seed=9000), params={"wait": 60})
        assert answer.status_code == 200, answer.text
        job = answer.headers["X-Job-Id"]
        assert roles.redis.client().exists(f"arq:result:{job}")  # the worker's queue user stored its end
        cached = roles.cache_redis
        assert cached is not None  # and its cache user the result (written beside the end, on another Redis)
        wait_until(lambda: cached.client().get(keys.cache_key(job)) is not None, 10, "the cached result")
    for kind in ("gateway", "worker"):
        own = roles.roles[kind]
        assert own["REDIS_URL"].startswith(f"redis://{kind}@") and own["PRECOND_CACHE_REDIS_URL"].startswith(
            f"redis://{kind}@")
        assert own["PRECOND_REDIS_PASSWORD_FILE"].endswith(f"redis-queue-{kind}-password")
        assert own["PRECOND_CACHE_REDIS_PASSWORD_FILE"].endswith(f"redis-cache-{kind}-password")


def test_password_file_completes_redis_urls(tmp_path: Path) -> None:
    password_file = tmp_path / "redis-password"
    password_file.write_text("s3cret-value\n")
    settings = QueueSettings(REDIS_URL="redis://redis:6379/0", cache_redis_url="redis://redis-cache:6379/1",
                             redis_password_file=password_file)
    assert settings.redis_dsn == "redis://:s3cret-value@redis:6379/0"
    assert settings.cache_redis_dsn == "redis://:s3cret-value@redis-cache:6379/1"
    explicit = QueueSettings(REDIS_URL="redis://:own@redis:6379/0", redis_password_file=password_file)
    assert explicit.redis_dsn == "redis://:own@redis:6379/0"  # a URL's own password wins
    assert explicit.cache_redis_dsn == explicit.redis_dsn  # no cache Redis of its own: the queue Redis
    cache_file = tmp_path / "redis-cache-gateway-password"
    cache_file.write_text("other\n")
    own = QueueSettings(REDIS_URL="redis://gateway@redis:6379/0", cache_redis_url="redis://gateway@redis-cache:6379/0",
                        redis_password_file=password_file, cache_redis_password_file=cache_file)
    assert own.redis_dsn == "redis://gateway:s3cret-value@redis:6379/0"  # the URL's user, the file's password
    assert own.cache_redis_dsn == "redis://gateway:other@redis-cache:6379/0"  # the cache Redis's own


async def _flood(url: str, secret: bytes, entries: int, size: int) -> tuple[dict[str, Any] | None, bool]:
    """Put `entries` results of `size` bytes through ResultCache; return the first one read back (evicted:
    None) and whether a fresh entry put after the flood reads back."""
    client: AsyncRedis[bytes] = AsyncRedis.from_url(url, password=PASSWORD)
    results = ResultCache(client, ttl_s=3600, secret=secret)
    ids = [f"check-{hashlib.sha256(str(i).encode()).hexdigest()}" for i in range(entries + 1)]
    try:
        for i, job_id in enumerate(ids[:-1]):
            await results.put(job_id, {"results": [], "pad": f"{i}:" + "x" * size})
            if i == 0:  # Redis's LRU clock ticks once a second: entries of the same second look as old as each
                await asyncio.sleep(1.1)  # other and allkeys-lru evicts among them by chance, the first one too
        first = await results.get(ids[0])
        await results.put(ids[-1], {"results": [], "fresh": True})
        fresh = await results.get(ids[-1]) == {"results": [], "fresh": True}
    finally:
        await client.aclose()  # type: ignore[attr-defined]  # types-redis predates aclose
    return first, fresh


def test_flooding_the_cache_evicts_cache_entries_never_queued_or_owed_work(stack: Stack) -> None:
    queue = queue_redis(stack)
    with stack.http() as client:
        with worker(stack):  # a finished job: its result is owed to clients for PRECOND_RESULT_TTL_S
            done = client.post("/check-actions", json=check_body("system.REQUEST('date')"), params={"wait": 30})
        assert done.status_code == 200, done.text
        finished = done.headers["X-Job-Id"]
        queued = []  # no worker now: these stay queued
        for seed in range(5):
            answer = client.post("/infer-preconditions", json=infer_body(seed=7000 + seed), params={"wait": 0})
            assert answer.status_code == 202, answer.text
            queued.append(answer.headers["X-Job-Id"])
        try:
            assert stack.cache_redis is not None
            # 3000 entries of 4 KB: 12 MB through a 2 MB cache Redis
            first, fresh = asyncio.run(_flood(stack.cache_redis.url, secret(stack), 3000, 4096))
            cache_info = cache_redis(stack).info()
            assert cache_info["evicted_keys"] > 0
            assert cache_info["used_memory"] <= CACHE_MAXMEMORY * 1.1
            assert first is None  # the oldest entries went
            assert fresh  # and the cache still answers
            # the queue Redis lost nothing: no eviction, every queued job and the finished job's result are there
            assert queue.info()["evicted_keys"] == 0
            for job_id in queued:
                assert queue.exists(f"arq:job:{job_id}")
                assert any(queue.zscore(name, job_id) is not None for name in keys.QUEUES)
                assert client.get(f"/jobs/{job_id}").json()["status"] == "queued"
            assert queue.exists(f"arq:result:{finished}")
            status = client.get(f"/jobs/{finished}").json()
            assert status["status"] == "succeeded" and status["result"] == done.json()
            again = client.post("/check-actions", json=check_body("system.REQUEST('date')"), params={"wait": 0})
            assert again.status_code == 200 and again.json() == done.json()
        finally:
            forget_queued(stack, queued)


def test_a_full_queue_redis_answers_503_and_keeps_what_it_accepted(stack: Stack) -> None:
    queue = queue_redis(stack)
    with stack.http() as client:
        accepted = client.post("/infer-preconditions", json=infer_body(seed=8000), params={"wait": 0})
        assert accepted.status_code == 202, accepted.text
        accepted_id = accepted.headers["X-Job-Id"]
        try:
            fillers = [f"test:filler:{i}" for i in range(64)]
            for name in fillers:
                queue.set(name, b"x" * 65536)
            # full: more in use than its maxmemory (noeviction: writes are refused, nothing is evicted)
            queue.config_set("maxmemory", int(queue.info()["used_memory"]) - 1024 * 1024)
            with pytest.raises(redis.ResponseError) as refused_write:
                queue.set("test:one-more", b"x")
            assert type(refused_write.value).__name__ == "OutOfMemoryError"
            for path, body in (("/infer-preconditions", infer_body(seed=8001)),
                               ("/check-actions", check_body("system.REQUEST('time')"))):
                refused = client.post(path, json=body, params={"wait": 0})
                assert refused.status_code == 503, refused.text
                assert refused.headers["Retry-After"] == RETRY_AFTER_S
                assert refused.json()["error"]["type"] == "unavailable"
            assert queue.info()["evicted_keys"] == 0 and queue.exists(*fillers) == len(fillers)
            assert queue.exists(f"arq:job:{accepted_id}")
            polled = client.get(f"/jobs/{accepted_id}")
            assert polled.status_code == 200 and polled.json()["status"] == "queued", polled.text  # reads work
        finally:
            queue.config_set("maxmemory", QUEUE_MAXMEMORY)
            queue.delete(*fillers)
        later = client.post("/infer-preconditions", json=infer_body(seed=8001), params={"wait": 0})
        assert later.status_code == 202, later.text  # room again: accepted
    forget_queued(stack, [accepted_id, later.headers["X-Job-Id"]])


def _signed(stack: Stack, stored: bytes | None, key: str) -> bool:
    return stored is not None and cache.unseal(secret(stack), key, stored) is not None


def _forgeries(stack: Stack, key: str, real: dict[str, Any]) -> dict[str, bytes]:
    lie = {"results": [{**verdict, "allowed": not verdict["allowed"], "violations": []}
                       for verdict in real["results"]]}
    payload = json.dumps(lie).encode()
    other_key = keys.cache_key("check-" + "0" * 64)
    return {
        "unsigned": payload,
        "bad signature": b"v1." + b"0" * 64 + b"." + payload,
        "another secret": cache.seal(b"not-the-deployment-secret", key, payload),
        "signed for another key": cache.seal(secret(stack), other_key, payload),
    }


def test_a_forged_cache_entry_is_never_served(stack: Stack) -> None:
    body = check_body("system.REQUEST('party_size')", "system.INFORM('price')")
    payload = CheckRequest.model_validate(body).model_dump(mode="json")
    job_id = keys.job_id("check", payload, None, secret(stack), keys.tenant_tag(secret(stack), "public"))
    key = keys.cache_key(job_id)
    queue, cached = queue_redis(stack), cache_redis(stack)
    with stack.http() as client, worker(stack):
        first = client.post("/check-actions", json=body, params={"wait": 30})
        assert first.status_code == 200 and first.headers["X-Job-Id"] == job_id
        real = first.json()
        CheckResponse.model_validate(real)
        # the worker caches a result as it records the job's end, not before: the answer may come first
        wait_until(lambda: cached.exists(key), 10, "the result cached")
        for name, forged in _forgeries(stack, key, real).items():
            queue.delete(f"arq:result:{job_id}")  # no result left but the cache entry: only running again can answer
            cached.set(key, forged)
            assert client.get(f"/jobs/{job_id}").status_code == 404, name  # not served as a finished job either
            assert not cached.exists(key), name  # ... and deleted on sight
            cached.set(key, forged)
            answer = client.post("/check-actions", json=body, params={"wait": 30})
            assert answer.status_code == 200, (name, answer.text)
            assert answer.json() == real, name
            assert queue.exists(f"arq:result:{job_id}"), name  # the job ran again
            wait_until(lambda: _signed(stack, cached.get(key), key), 10, f"{name}: the entry re-signed")
        assert client.post("/check-actions", json=body, params={"wait": 0}).json() == real  # a real hit
    gateway_log = b"".join(path.read_bytes() for path in stack.logs.glob("gateway-*.log"))
    assert b"is not signed by this deployment" in gateway_log


def test_every_key_expires_or_is_bounded(stack: Stack) -> None:
    with stack.http() as client, worker(stack):
        for answer in (
            client.post("/infer-preconditions", json=infer_body(seed=9000), params={"wait": 60}),
            client.post("/check-actions", json=check_body("system.REQUEST('cuisine')"), params={"wait": 30}),
        ):
            assert answer.status_code == 200, answer.text
        made = client.post("/precondition-sets", json={"spec": SPEC, "demonstrations": DEMOS[:2],
                                                      "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]}})
        assert made.status_code == 201, made.text
        trained = client.post("/policies", params={"wait": 60}, json={
            "spec": SPEC, "demonstrations": DEMOS[:1], "options": {"steps": 1, "max_tokens": 1024}})
        assert trained.status_code == 200, trained.text
        queue = queue_redis(stack)
        names = sorted(key.decode() for key in queue.scan_iter(count=1000))
        assert any(name.startswith("precond:progress:") for name in names)  # the audit saw the job's keys
        assert any(name.startswith("precond:worker:") for name in names)
        assert any(name.startswith("arq:result:") for name in names)
        assert any(name.startswith("precond:set:") for name in names)
        assert any(name.startswith("precond:policy:") for name in names)
        for name in names:
            if name in BOUNDED_KEYS:
                continue
            if name.startswith(("precond:policy:", "precond:policies:", "precond:policy-bytes:")):  # bounded data
                fields = GatewaySettings.model_fields
                if name.startswith("precond:policy-bytes:"):
                    assert int(queue.get(name) or 0) <= int(fields["max_policy_bytes_per_tenant"].default)
                elif name.startswith("precond:policies:"):
                    assert queue.scard(name) <= int(fields["max_policies_per_tenant"].default)
                else:  # `latest` and three fields per version (the policy, its weights, the job that stored it)
                    assert queue.hlen(name) <= 3 * int(fields["max_policy_versions"].default) + 1
                continue
            if name.startswith(("precond:set:", "precond:sets:", "precond:set-bytes:")):  # a client's data: bounded
                fields = GatewaySettings.model_fields
                if name.startswith("precond:set-bytes:"):  # one counter per tenant
                    assert int(queue.get(name) or 0) <= int(fields["max_set_bytes_per_tenant"].default)
                elif name.startswith("precond:sets:"):
                    assert queue.scard(name) <= int(fields["max_sets_per_tenant"].default)
                else:  # `latest` and one field per version
                    assert queue.hlen(name) <= int(fields["max_set_versions"].default) + 1
                continue
            assert queue.pttl(name) != -1, f"{name} never expires"  # -2: gone meanwhile (expired)
        for name in keys.QUEUES:
            assert queue.zcard(name) <= QUEUE_MAX_JOBS
        assert queue.hlen(keys.RUNNING_KEY) <= 5  # at most one claim per job the one worker runs (1 + 4)
        assert queue.hlen(keys.UNCLAIMED_KEY) <= len(keys.QUEUES) * QUEUE_MAX_JOBS  # only queued jobs
        for field in queue.hkeys(keys.STATS_KEY):
            table = field.decode().split(":")[0]
            assert table in ("jobs", "phase_sum", "phase_count", "queue_sum", "queue_count", "sandbox_failures"), field
        cache_keys = [key.decode() for key in cache_redis(stack).scan_iter(count=1000)]
        assert cache_keys
        for name in cache_keys:
            assert name.startswith("precond:cache:"), f"{name} in the cache Redis"
            assert cache_redis(stack).pttl(name) != -1, f"{name} never expires"  # -2: evicted meanwhile
        assert not any(name.startswith("precond:cache:") for name in names)  # the cache is the cache Redis's
        wait_until(lambda: not queue.hlen(keys.RUNNING_KEY), 10, "the finished jobs' claims to go")
