"""The Python client against a real stack with API keys: typed round trips, typed errors, 202s followed to the
end, cancellation, and 429s retried after their Retry-After."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import pytest

from precond.jobs.queue.keys import tenant_tag
from precond.stack.keyed import KeyedStack
from precond.stack.local import ROOT, check_body, heavy_infer_body, infer_body, slow_model_body
from precond_client import (
    AsyncClient,
    Cancelled,
    CheckRequest,
    CheckResponse,
    Client,
    InferRequest,
    InferResponse,
    InvalidInput,
    JobStatus,
    NotFound,
    PrecondError,
    RateLimited,
    Retry,
    Unauthorized,
    Unavailable,
)

SECRET = "stack-secret-for-tests"


def test_the_client_imports_without_torch_transformers_or_fastapi() -> None:
    probe = "import sys, precond_client; print(json.dumps(sorted(m for m in {'torch', 'transformers', 'fastapi', " \
            "'uvicorn', 'redis', 'arq'} if m in sys.modules)))"
    done = subprocess.run([sys.executable, "-c", "import json; " + probe], cwd=ROOT, capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


def test_check_actions_round_trip(keyed: KeyedStack) -> None:
    request = CheckRequest.model_validate(check_body("system.INFORM('phone_number')", "system.REQUEST('cuisine')"))
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client:
        answer = client.check_actions(request, wait=30)
        assert client.health()["status"] == "ok"
        try:  # the worker loads its model lazily: either answer is typed, and neither waits
            assert client.ready()["status"] == "ready"
        except Unavailable as not_ready:
            assert not_ready.status == 503 and "model" in not_ready.message
    assert isinstance(answer, CheckResponse)
    verdicts = {v.call: v for v in answer.results}
    inform = verdicts["system.INFORM('phone_number')"]
    assert not inform.allowed and inform.violations == ["self.user.requested_slot[slot]"]
    assert verdicts["system.REQUEST('cuisine')"].allowed


def test_the_async_client_speaks_the_same(keyed: KeyedStack) -> None:
    async def run() -> tuple[CheckResponse, dict[str, object]]:
        async with AsyncClient(keyed.url, api_key=keyed.keys["acme"]) as client:
            answer = await client.check_actions(check_body("system.FindRestaurants()"), wait=30)  # a dict works
            return answer, await client.health()

    answer, health = asyncio.run(run())
    assert [v.call for v in answer.results] == ["system.FindRestaurants()"]
    assert not answer.results[0].allowed and health["status"] == "ok"


def test_a_422_is_invalid_input_with_its_field(keyed: KeyedStack) -> None:
    body = infer_body(seed=7)
    body["demonstrations"][1] += "user.INFORM('city'\n"
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client, \
            pytest.raises(InvalidInput) as raised:
        client.infer_preconditions(body)
    assert raised.value.status == 422 and raised.value.field == "demonstrations[1]"
    assert "SyntaxError" in raised.value.message and raised.value.request_id


def test_a_bad_field_is_invalid_input_before_anything_is_sent(keyed: KeyedStack) -> None:
    body = {**check_body(), "calls": []}
    with Client(keyed.url, api_key="no key needed: never sent") as client, \
            pytest.raises(InvalidInput) as raised:
        client.check_actions(body)
    assert raised.value.field == "calls" and raised.value.status is None


def test_a_missing_or_unknown_key_is_unauthorized(keyed: KeyedStack) -> None:
    for key in (None, "pk_not-a-key"):
        with Client(keyed.url, api_key=key) as client, pytest.raises(Unauthorized) as raised:
            client.check_actions(check_body())
        assert raised.value.status == 401 and raised.value.type == "unauthorized"
    with Client(keyed.url) as anonymous:
        assert anonymous.health()["status"] == "ok"  # open endpoints need no key


def test_a_202_is_followed_to_completion_with_progress(keyed: KeyedStack) -> None:
    seen: list[JobStatus] = []
    body = heavy_infer_body(seed=101, millions=5)
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client:
        answer = client.infer_preconditions(body, wait=0, progress=seen.append, timeout=300)
    assert isinstance(answer, InferResponse)
    assert "self.user.requested_slot[slot]" in answer.preconditions["SYSTEM.INFORM"]
    assert seen, "the progress callback was never called"
    assert seen[0].status in ("queued", "running") and seen[-1].status == "succeeded"
    last = seen[-1].progress
    assert last.phase == "done" and last.done == last.total > 0, last  # never `done 0 0`
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client:  # the same again: a 200 from the cache
        cached: list[JobStatus] = []
        client.infer_preconditions(body, wait=30, progress=cached.append)
    assert [s.progress.model_dump() for s in cached] == [{"phase": "done", "done": 1, "total": 1}]
    assert len({s.id for s in seen}) == 1 and seen[0].id.startswith("infer-")


def test_a_job_can_be_cancelled_and_then_reads_cancelled(keyed: KeyedStack) -> None:
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client:
        submitted = client.submit(CheckRequest.model_validate(check_body()), wait=30)
        assert submitted.status == "succeeded" and submitted.result is not None  # done within the wait
        job = client.submit(_model_request(seed=202), wait=0)
        assert job.status in ("queued", "running")
        assert client.cancel(job.id).status == "cancelled"
        with pytest.raises(Cancelled):
            client.result(job.id, timeout=60)
        with pytest.raises(NotFound) as raised:
            client.job("check-" + "0" * 16 + "-" + "0" * 48)
        assert raised.value.status == 404


def _model_request(seed: int) -> InferRequest:
    return InferRequest.model_validate(slow_model_body(seed))


def _empty_bucket(keyed: KeyedStack, tenant: str) -> None:
    """No token for the next two seconds, then one a second: the bucket stamped a second ahead of Redis's own clock
    (the bucket's clock, which never goes back, so a stamp an hour ahead would refuse for an hour)."""
    tag = tenant_tag(SECRET.encode(), tenant)
    redis = keyed.stack.redis.client()
    seconds, micros = redis.time()
    redis.hset(f"precond:tenant:{tag}:rate", mapping={"tokens": 0, "at": seconds + micros / 1e6 + 1})


def test_a_429_is_retried_after_its_retry_after(keyed: KeyedStack) -> None:
    retries: list[tuple[PrecondError, float]] = []
    _empty_bucket(keyed, "throttled")
    with Client(keyed.url, api_key=keyed.keys["throttled"],
                on_retry=lambda error, delay: retries.append((error, delay))) as client:
        answer = client.check_actions(check_body("system.REQUEST('city')"), wait=30)
    assert answer.results[0].call == "system.REQUEST('city')"
    error, delay = retries[0]
    assert isinstance(error, RateLimited) and error.limit == "rate_limited" and error.retry_after == 1
    assert delay >= 1  # Retry-After is a floor


def test_a_429_past_the_last_attempt_is_rate_limited(keyed: KeyedStack) -> None:
    _empty_bucket(keyed, "throttled")
    with Client(keyed.url, api_key=keyed.keys["throttled"], retry=Retry(attempts=1)) as client, \
            pytest.raises(RateLimited) as raised:
        client.check_actions(check_body())
    assert raised.value.status == 429 and raised.value.limit == "rate_limited"
    assert raised.value.retry_after is not None and raised.value.retry_after >= 1
