"""The HTTP contract end to end: gateway (uvicorn) → Redis (arq) → worker process → back."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx

from tests.service.conftest import SPEC, Stack, infer_body, wait_until


def jobs_started(stack: Stack) -> int:
    return sum(int(str(beat["jobs_started"])) for beat in stack.heartbeats())


def test_infer_end_to_end_then_cache_hit_never_reaches_a_worker(stack: Stack, client: httpx.Client) -> None:
    body = infer_body(seed=101)
    first = client.post("/infer-preconditions", json=body)
    assert first.status_code == 200, first.text
    assert set(first.json()["preconditions"]) == {"SYSTEM.REQUEST"}
    wait_until(lambda: jobs_started(stack) >= 1, 5, "heartbeat to count the job")
    started = jobs_started(stack)

    second = client.post("/infer-preconditions", json=body)
    assert second.status_code == 200
    assert second.json() == first.json()
    assert second.headers["X-Job-Id"] == first.headers["X-Job-Id"]
    time.sleep(1.2)  # two heartbeats: a job the worker ran would show in its count by now
    assert jobs_started(stack) == started
    assert 'precond_cache_total{kind="infer",result="hit"} 1.0' in client.get("/metrics").text


def test_job_progress_poll_and_cancel(client: httpx.Client) -> None:
    slow = infer_body(SPEC + "# slow: 20\n", seed=102)
    accepted = client.post("/infer-preconditions", json=slow, params={"wait": 0.3})
    assert accepted.status_code == 202
    location = accepted.headers["Location"]
    assert accepted.json()["status"] in ("queued", "running")
    wait_until(lambda: client.get(location).json()["progress"]["phase"] == "generate", 5, "progress")
    cancelled = client.delete(location)
    assert cancelled.status_code == 200
    wait_until(lambda: client.get(location).json()["status"] == "cancelled", 5, "cancellation")
    assert client.post("/infer-preconditions", json=slow, params={"wait": 0}).status_code == 202  # runs again
    client.delete(location)


def test_check_actions_does_not_queue_behind_model_jobs(client: httpx.Client) -> None:
    slow = infer_body(SPEC + "# slow: 20\n", seed=103)
    location = client.post("/infer-preconditions", json=slow, params={"wait": 0}).headers["Location"]
    check = {
        "spec": SPEC,
        "history": "user = USER()\nsystem = SYSTEM(user)\n",
        "calls": ["system.REQUEST('x')"],
    }
    answer = client.post("/check-actions", json=check, params={"wait": 5})
    assert answer.status_code == 200, answer.text
    assert answer.json()["results"][0]["allowed"] is True
    client.delete(location)


def test_malformed_body_is_422_with_field_path(client: httpx.Client) -> None:
    body = infer_body()
    body["demonstrations"] = ["ok", "ok", "ok", 7]
    answer = client.post("/infer-preconditions", json=body, headers={"X-Request-Id": "req-42"})
    assert answer.status_code == 422
    assert answer.headers["X-Request-Id"] == "req-42"
    assert answer.json() == {
        "error": {
            "type": "validation_error",
            "message": "Input should be a valid string",
            "field": "demonstrations.3",
        },
        "request_id": "req-42",
    }


def test_spec_that_does_not_parse_is_422_with_line(client: httpx.Client) -> None:
    answer = client.post("/infer-preconditions", json=infer_body("class A:\n  def f(self):\n    return (\n"))
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == "spec" and "line" in error["message"]
    assert answer.json()["request_id"] == answer.headers["X-Request-Id"]


def test_unknown_action_is_422(client: httpx.Client) -> None:
    answer = client.post("/infer-preconditions", json={**infer_body(), "actions": ["SYSTEM.NOPE"]})
    assert answer.status_code == 422
    assert answer.json()["error"]["type"] == "unknown_action"
    assert answer.json()["error"]["field"] == "actions[0]"


def test_oversized_body_is_413_declared_or_streamed(client: httpx.Client) -> None:
    big = infer_body()
    big["demonstrations"] = ["x" * 70_000]
    declared = client.post("/infer-preconditions", json=big)
    assert declared.status_code == 413
    assert declared.json()["error"]["type"] == "body_too_large"

    def chunks() -> Iterator[bytes]:  # no Content-Length: the bound is enforced while reading
        yield b'{"spec": "'
        for _ in range(100):
            yield b"x" * 1000
        yield b'"}'

    streamed = client.post("/check-actions", content=chunks(), headers={"Content-Type": "application/json"})
    assert streamed.status_code == 413


def test_hostile_bytes_are_4xx_not_500(client: httpx.Client) -> None:
    headers = {"Content-Type": "application/json"}
    assert client.post("/check-actions", content=b'{"spec": "\xff\xfe"}', headers=headers).status_code in (
        400,
        422,
    )
    nested = b"[" * 20_000 + b"]" * 20_000
    answer = client.post("/check-actions", content=nested, headers=headers)
    assert answer.status_code in (400, 422), answer.text
    assert "error" in answer.json()


def test_full_queue_is_429_with_retry_after(client: httpx.Client) -> None:
    locations = []
    for seed in range(200, 206):  # bound is 3 (queued + running); the worker takes one at a time
        answer = client.post(
            "/infer-preconditions", json=infer_body(SPEC + "# slow: 20\n", seed=seed), params={"wait": 0}
        )
        if answer.status_code == 429:
            break
        locations.append(answer.headers["Location"])
    assert answer.status_code == 429
    assert int(answer.headers["Retry-After"]) > 0
    assert answer.json()["error"]["type"] == "queue_full"
    for location in locations:
        client.delete(location)


def test_unknown_job_is_404(client: httpx.Client) -> None:
    for job_id in ("infer-" + "0" * 64, "not-a-job"):
        answer = client.get(f"/jobs/{job_id}")
        assert answer.status_code == 404
        assert answer.json()["error"]["type"] == "not_found"
    assert client.delete("/jobs/check-" + "0" * 64).status_code == 404


def test_health_ready_metrics(client: httpx.Client) -> None:
    assert client.get("/health").json() == {"status": "ok"}
    ready = client.get("/ready")
    assert ready.status_code == 200 and ready.json()["model_loaded"] >= 1
    text = client.get("/metrics").text
    for name in (
        "precond_http_requests_total",
        "precond_queue_depth",
        "precond_jobs_total",
        "precond_workers",
    ):
        assert name in text
