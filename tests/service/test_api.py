"""The HTTP contract end to end: gateway (uvicorn) → Redis (arq) → worker process (real engine) → back."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import redis

from precond.gateway.http_protocol import MAX_REQUEST_HEAD_BYTES, MAX_URL_BYTES
from precond.jobs import cache
from precond.jobs.queue import keys
from precond.stack.local import (
    Stack,
    check_body,
    example,
    infer_body,
    slow_model_body,
    wait_until,
)
from precond_client.schemas import CheckRequest


def jobs_started(stack: Stack) -> int:
    return sum(int(str(beat["jobs_started"])) for beat in stack.heartbeats())


def test_infer_end_to_end_then_cache_hit_never_reaches_a_worker(stack: Stack, client: httpx.Client) -> None:
    body = infer_body(seed=101)
    first = client.post("/infer-preconditions", json=body)
    assert first.status_code == 200, first.text
    result = first.json()
    assert "SYSTEM.REQUEST" in result["preconditions"]
    assert "self.user.no_more" in result["preconditions"]["SYSTEM.GOODBYE"]  # the demos' rule, found for real
    assert "assert self.user.no_more" in result["program"]
    assert result["stats"]["total"]["valid"] > 0 and result["model"] is None
    wait_until(lambda: jobs_started(stack) >= 1, 5, "heartbeat to count the job")
    started = jobs_started(stack)

    second = client.post("/infer-preconditions", json=body)
    assert second.status_code == 200
    assert second.json() == result
    assert second.headers["X-Job-Id"] == first.headers["X-Job-Id"]
    time.sleep(1.2)  # two heartbeats: a job the worker ran would show in its count by now
    assert jobs_started(stack) == started
    assert 'precond_cache_total{kind="infer",result="hit"} 1.0' in client.get("/metrics").text


def test_unfinished_job_is_202_then_polled_to_its_result(client: httpx.Client) -> None:
    accepted = client.post("/infer-preconditions", json=infer_body(seed=111), params={"wait": 0})
    assert accepted.status_code == 202, accepted.text
    location = accepted.headers["Location"]
    assert location == f"/jobs/{accepted.headers['X-Job-Id']}"
    wait_until(lambda: client.get(location).json()["status"] == "succeeded", 30, "the job to finish")
    done = client.get(location).json()
    assert done["progress"]["phase"] == "done"
    assert "self.user.no_more" in done["result"]["preconditions"]["SYSTEM.GOODBYE"]


def test_next_action_with_the_tiny_model_reports_its_rejections(client: httpx.Client) -> None:
    body = example("next-action")
    body["options"] = {"mode": "sample", "max_attempts": 3, "max_new_tokens": 16}
    answer = client.post("/next-action", json=body, params={"wait": 60})
    assert answer.status_code == 200, answer.text
    (action,) = answer.json()["actions"]
    # The tiny model writes noise: Algorithm 1 rejects every sample, and says why.
    assert action["verified"] is False
    assert action["attempts"] == 3 and len(action["rejected"]) == 3
    assert all(rejection["reason"] for rejection in action["rejected"])
    assert answer.json()["model"]["device"] == "cpu"


def test_next_action_constrained_with_the_tiny_model_chooses_an_allowed_call(client: httpx.Client) -> None:
    body = example("next-action")
    body["options"] = {"mode": "constrained", "return_allowed": True}
    answer = client.post("/next-action", json=body, params={"wait": 60})
    assert answer.status_code == 200, answer.text
    assert answer.json()["mode"] == "constrained"
    (action,) = answer.json()["actions"]
    assert action["verified"] and action["call"] in {a["call"] for a in action["allowed"]}


@pytest.mark.parametrize("options", [{"mode": "constrained", "verify": False}, {"fallback": "greedy"},
                                     {"mode": "guess"}])
def test_next_action_options_that_do_not_fit_the_mode_are_422(client: httpx.Client, options: dict[str, Any]
                                                               ) -> None:
    body = example("next-action") | {"options": options}
    answer = client.post("/next-action", json=body, params={"wait": 0})
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"]["field"].startswith("options"), answer.json()


def test_job_progress_poll_and_cancel(client: httpx.Client) -> None:
    slow = slow_model_body(seed=102)
    accepted = client.post("/infer-preconditions", json=slow, params={"wait": 0.3})
    assert accepted.status_code == 202
    location = accepted.headers["Location"]
    assert accepted.json()["status"] in ("queued", "running")
    wait_until(lambda: client.get(location).json()["progress"]["phase"] == "generate", 20, "progress")
    assert client.get(location).json()["status"] == "running"
    cancelled = client.delete(location)
    assert cancelled.status_code == 200
    wait_until(lambda: client.get(location).json()["status"] == "cancelled", 10, "cancellation")
    assert client.post("/infer-preconditions", json=slow, params={"wait": 0}).status_code == 202  # runs again
    client.delete(location)


def test_check_actions_does_not_queue_behind_model_jobs(client: httpx.Client) -> None:
    location = client.post(
        "/infer-preconditions", json=slow_model_body(seed=103), params={"wait": 0}
    ).headers["Location"]
    try:
        wait_until(lambda: client.get(location).json()["status"] == "running", 20, "the model job to start")
        answer = client.post("/check-actions", json=check_body(), params={"wait": 10})
        assert answer.status_code == 200, answer.text
        assert client.get(location).json()["status"] == "running"
    finally:
        client.delete(location)
    find, inform = answer.json()["results"]
    assert find == {
        "call": "system.FindRestaurants()",
        "action": "SYSTEM.FindRestaurants",
        "rule_status": "given",  # inline rules: no inference's word on how they were decided
        "allowed": False,
        "violations": ["self.user.informed_slot['cuisine']"],
        "decided": {},  # rules sent inline, without an inference's report
        "error": None,
    }
    assert inform["allowed"] is False and inform["violations"] == ["self.user.requested_slot[slot]"]


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


def test_a_form_body_is_422_naming_the_body_and_the_content_type(client: httpx.Client) -> None:
    answer = client.post("/check-actions", data={"spec": "x", "history": "", "calls": "a.b()"})
    assert answer.status_code == 422
    error = answer.json()["error"]
    assert error["field"] == "body" and "application/json" in error["message"]
    assert "application/x-www-form-urlencoded" in error["message"]


@pytest.mark.parametrize(("body", "field", "message"), [
    ({"history": "", "calls": ["a.b()"]}, "body", "give `spec` (with `preconditions`) or `precondition_set`"),
    ({"spec": "x", "history": "", "options": {"verify": False}}, "options",
     "verify: false needs mode 'sample' (mode 'constrained' only returns allowed calls)"),
])
def test_a_validator_message_is_the_services_words(client: httpx.Client, body: dict[str, Any], field: str,
                                                    message: str) -> None:
    path = "/check-actions" if "calls" in body else "/next-action"
    answer = client.post(path, json=body)
    assert answer.status_code == 422
    assert answer.json()["error"] == {"type": "validation_error", "message": message, "field": field}


@pytest.mark.parametrize("tolerance", [-0.01, 0.51, "often", None, "nan"])
def test_a_tolerance_outside_0_to_half_or_not_a_number_is_422_naming_it(
    client: httpx.Client, tolerance: object
) -> None:
    body = infer_body()
    body["options"]["tolerance"] = tolerance
    answer = client.post("/infer-preconditions", json=body)
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"]["field"] == "options.tolerance"


@pytest.mark.parametrize(("option", "value"), [("unseen", "maybe"), ("unseen", None), ("ranking", "safe"),
                                               ("ranking", 3)])
def test_a_safety_setting_outside_its_values_is_422_naming_it(client: httpx.Client, option: str,
                                                               value: object) -> None:
    body = infer_body()
    body["options"][option] = value
    answer = client.post("/infer-preconditions", json=body)
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == f"options.{option}"
    assert ("'cautious'" if option == "ranking" else "'refuse'") in error["message"], error["message"]


def test_spec_that_does_not_parse_is_422_with_line(client: httpx.Client) -> None:
    answer = client.post("/infer-preconditions", json=infer_body(spec="class A:\n  def f(self):\n    return (\n"))
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error == {
        "type": "invalid_program",
        "message": "spec, line 3: SyntaxError: '(' was never closed",
        "field": "spec",
    }
    assert answer.json()["request_id"] == answer.headers["X-Request-Id"]


def test_demonstration_that_raises_is_422_naming_it_and_its_line(client: httpx.Client) -> None:
    demos = example("infer-enumerate")["demonstrations"]
    raising = "user = USER()\nsystem = SYSTEM(user)\nsystem.REQUEST('city')\nuser.NOPE()\n"
    answer = client.post("/infer-preconditions", json=infer_body(demonstrations=[demos[0], raising]))
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"] == {
        "type": "invalid_program",
        "message": "demonstrations[1], line 4: AttributeError: 'USER' object has no attribute 'NOPE'",
        "field": "demonstrations[1]",
    }


def test_unknown_action_is_422(client: httpx.Client) -> None:
    answer = client.post("/infer-preconditions", json=infer_body(actions=["SYSTEM.NOPE"]))
    assert answer.status_code == 422
    assert answer.json()["error"]["type"] == "unknown_action"
    assert answer.json()["error"]["field"] == "actions[0]"


@pytest.mark.parametrize(("call", "words"), [
    ("user.AFFIRM()", "USER.AFFIRM is not one of the agent's actions"),
    ("system.REQUESTT('city')", "(did you mean 'SYSTEM.REQUEST'?)"),
])
def test_a_proposed_call_of_no_action_is_422_never_approved(client: httpx.Client, call: str, words: str) -> None:
    answer = client.post("/check-actions", json=check_body("system.GOODBYE()", call), params={"wait": 30})
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["type"] == "unknown_action" and error["field"] == "calls[1]" and words in error["message"]


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
    for seed in range(200, 206):  # bound is 3 (queued + running); the worker takes one model job at a time
        answer = client.post("/infer-preconditions", json=slow_model_body(seed), params={"wait": 0})
        if answer.status_code == 429:
            break
        locations.append(answer.headers["Location"])
    assert answer.status_code == 429
    assert len(locations) == 3
    assert int(answer.headers["Retry-After"]) > 0
    assert answer.json()["error"]["type"] == "queue_full"
    for location in locations:
        client.delete(location)


def test_internal_error_is_500_with_the_request_id(stack: Stack, client: httpx.Client) -> None:
    body = check_body("system.REQUEST('party_size')")
    payload = CheckRequest.model_validate(body).model_dump(mode="json")
    job_id = keys.job_id("check", payload, None, stack.env["PRECOND_SECRET"].encode(),
                       keys.tenant_tag(stack.env["PRECOND_SECRET"].encode(), "public"))
    corrupt: redis.Redis[bytes] = stack.redis.client()
    key = keys.cache_key(job_id)
    # a fault the gateway does not expect: an entry signed with the deployment's secret that is not JSON
    corrupt.set(key, cache.seal(stack.env["PRECOND_SECRET"].encode(), key, b"{not json"))
    try:
        answer = client.post("/check-actions", json=body, headers={"X-Request-Id": "req-500"})
    finally:
        corrupt.delete(keys.cache_key(job_id))
    assert answer.status_code == 500
    assert answer.headers["X-Request-Id"] == "req-500"
    assert answer.json() == {
        "error": {"type": "internal", "message": "internal error; quote the request id when reporting it"},
        "request_id": "req-500",
    }


def test_unknown_job_is_404(client: httpx.Client) -> None:
    for job_id in ("infer-" + "0" * 64, "not-a-job"):
        answer = client.get(f"/jobs/{job_id}")
        assert answer.status_code == 404
        assert answer.json()["error"]["type"] == "not_found"
    assert client.delete("/jobs/check-" + "0" * 64).status_code == 404


def _raw_get(stack: Stack, path: str) -> tuple[int, bytes]:
    """A GET whose head arrives in two reads: 20 KiB, a pause, the rest (the way a slow client sends it)."""
    head = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n".encode()
    with socket.create_connection(("127.0.0.1", stack.port), timeout=30) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(head[:20_000])
        time.sleep(0.3)  # not needed to pass: it makes the split reliable, which is the attack
        conn.sendall(head[20_000:])
        answer = b""
        while chunk := conn.recv(65536):
            answer += chunk
    status_line, _, rest = answer.partition(b"\r\n")
    return int(status_line.split()[1]), rest.partition(b"\r\n\r\n")[2]


def test_a_long_url_sent_in_pieces_gets_the_apps_json_error(stack: Stack) -> None:
    """h11's default 16 KiB head buffer made a 60 KiB URL a plain-text 400 or the app's JSON 404 depending on
    how TCP split it (a CI run failed on it); under the gateway's bounds the app always answers (a URL up to
    `MAX_URL_BYTES`, httptools' URL parser's own bound)."""
    status, body = _raw_get(stack, "/jobs/infer-" + "0" * (MAX_URL_BYTES - 1024))
    assert status == 404 and json.loads(body)["error"]["type"] == "not_found"


def _endless_head(stack: Stack, start: bytes, piece: bytes, pause_s: float, budget: int) -> tuple[bytes, int]:
    """Sends `start`, then `piece` after `piece` (never the blank line that ends a head) until the server answers
    or closes, or `budget` bytes went out: what it answered, and how many bytes it had been sent by then."""
    sent = 0
    with socket.create_connection(("127.0.0.1", stack.port), timeout=30) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(start)
        conn.settimeout(pause_s or 0.001)
        while sent < budget:
            try:
                conn.sendall(piece)
            except OSError:  # reset: the server closed while we were still sending
                break
            sent += len(piece)
            try:
                if conn.recv(65536, socket.MSG_PEEK):
                    break
            except TimeoutError:
                continue
        conn.settimeout(10)
        answer = b""
        try:
            while chunk := conn.recv(65536):
                answer += chunk
        except (TimeoutError, ConnectionResetError):
            pass
    return answer, sent


@pytest.mark.parametrize("start,piece", [
    (b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n", b"X-Filler: " + b"a" * 1000 + b"\r\n"),  # many headers
    (b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Long: ", b"a" * 1024),  # one header's value, in pieces
    (b"GET /health?q=", b"a" * 1024),  # the URL, in pieces
], ids=["headers", "value", "url"])
def test_a_head_that_never_ends_is_refused_at_the_bound(stack: Stack, start: bytes, piece: bytes) -> None:
    """httptools keeps a head's URL and header values for as long as they come; without the gateway's bound
    this client, sending 4 MiB, got no answer at all and the gateway held all of it."""
    answer, sent = _endless_head(stack, start, piece, 0.0, 4 << 20)
    assert answer.startswith(b"HTTP/1.1 400 "), answer[:100]
    assert b"connection: close" in answer.lower()
    assert sent <= MAX_REQUEST_HEAD_BYTES + (1 << 20)  # refused near the bound (one read, socket buffers)


def test_a_head_trickled_in_many_reads_is_refused(stack: Stack) -> None:
    """Few bytes a read: each read would copy the whole URL so far again (quadratic); 256 reads at most."""
    answer, sent = _endless_head(stack, b"GET /health?q=", b"a" * 8, 0.002, 64 << 10)
    assert answer.startswith(b"HTTP/1.1 400 "), answer[:100]
    assert sent < 32 << 10  # long before the byte bound


def test_a_whole_head_past_the_bound_is_refused_however_it_arrives(stack: Stack) -> None:
    fillers = "".join(f"X-Filler-{i}: {'a' * (MAX_REQUEST_HEAD_BYTES // 3)}\r\n" for i in range(4))
    head = f"GET /health HTTP/1.1\r\nHost: x\r\n{fillers}\r\n".encode()
    with socket.create_connection(("127.0.0.1", stack.port), timeout=30) as conn:
        conn.sendall(head)
        answer = b""
        while chunk := conn.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 400 "), answer[:100]


def test_health_ready_metrics(client: httpx.Client) -> None:
    assert client.get("/health").json() == {"status": "ok", "sandbox": "confined"}
    wait_until(lambda: client.get("/ready").status_code == 200, 20, "the worker's model to load")
    assert client.get("/ready").json()["model_loaded"] >= 1
    text = client.get("/metrics").text
    for name in (
        "precond_http_requests_total",
        "precond_queue_depth",
        "precond_jobs_total",
        "precond_workers",
        "precond_job_phase_seconds",
    ):
        assert name in text


def test_every_answer_says_its_content_type_is_not_to_be_sniffed(client: httpx.Client) -> None:
    """A JSON answer echoes caller text (a job's result, an error quoting the input): a browser must never read it
    as HTML or script, whatever it contains."""
    html = "<script>alert(1)</script>"
    answers = [
        client.get("/health"), client.get("/metrics"),
        client.post("/check-actions", json=check_body(f"system.REQUEST('{html}')")),
        client.post("/check-actions", json={**check_body(), "spec": html}),
        client.get(f"/jobs/{html}"),
        client.post("/check-actions", content=b"{" * 70_000, headers={"Content-Type": "application/json"}),
    ]
    assert {a.status_code for a in answers} >= {200, 404, 422, 413}
    for answer in answers:
        assert answer.headers.get("X-Content-Type-Options") == "nosniff", (answer.status_code, answer.headers)


def test_programs_are_checked_at_the_gateway_before_any_queueing(client: httpx.Client) -> None:
    demos = example("infer-enumerate")["demonstrations"]
    broken = [demos[0], demos[1], "user = USER()\nsystem.REQUEST('city'\n"]
    answer = client.post("/infer-preconditions", json=slow_model_body(seed=120) | {"demonstrations": broken},
                         params={"wait": 0})  # a job would answer 202 here: the 422 comes before the queue
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["type"] == "invalid_program" and error["field"] == "demonstrations[2]"
    assert error["message"].startswith("demonstrations[2], line 2: SyntaxError:")

    body = example("next-action") | {"history": "user = USER(\n"}
    answer = client.post("/next-action", json=body, params={"wait": 0})
    assert answer.status_code == 422 and answer.json()["error"]["field"] == "history", answer.text

    no_action = ["user = USER()\nsystem = SYSTEM(user)\nuser.INFORM('city')\n"] * 2
    answer = client.post("/infer-preconditions", json=infer_body(seed=121, demonstrations=no_action),
                         params={"wait": 0})
    assert answer.status_code == 422, answer.text
    assert answer.json()["error"]["field"] == "demonstrations"
    assert "none of the 2 demonstrations calls any of the actions" in answer.json()["error"]["message"]


def test_malformed_json_names_the_body_and_where(client: httpx.Client) -> None:
    answer = client.post("/check-actions", content=b'{"spec": "x",\n  "history": oops}',
                         headers={"Content-Type": "application/json"})
    assert answer.status_code == 422
    assert answer.json()["error"] == {
        "type": "validation_error",
        "message": "body is not valid JSON: Expecting value at line 2, column 14 (character 27)",
        "field": "body",
    }


def test_rule_errors_say_how_to_fix_them(client: httpx.Client) -> None:
    body = check_body()
    body["preconditions"] = {"SYSTEM.INFORM": ["assert self.user.requested_slot[slot]"]}
    answer = client.post("/check-actions", json=body)
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == "preconditions.SYSTEM.INFORM[0]"
    assert "write the expression without `assert`" in error["message"]
    body["preconditions"] = {"SYSTEM.INFROM": ["self.user.requested_slot[slot]"]}
    error = client.post("/check-actions", json=body).json()["error"]
    assert error["type"] == "unknown_action" and error["field"] == "preconditions.SYSTEM.INFROM"
    assert "did you mean 'SYSTEM.INFORM'?" in error["message"]
    answer = client.post("/infer-preconditions", json=infer_body(actions=["SYSTEM.REQEST"]))
    assert "did you mean 'SYSTEM.REQUEST'?" in answer.json()["error"]["message"]


def test_enumerate_inference_does_not_queue_behind_model_jobs(client: httpx.Client) -> None:
    location = client.post(
        "/infer-preconditions", json=slow_model_body(seed=130), params={"wait": 0}
    ).headers["Location"]
    try:
        wait_until(lambda: client.get(location).json()["status"] == "running", 20, "the model job to start")
        answer = client.post("/infer-preconditions", json=infer_body(seed=131), params={"wait": 20})
        assert answer.status_code == 200, answer.text
        assert "self.user.no_more" in answer.json()["preconditions"]["SYSTEM.GOODBYE"]
        assert client.get(location).json()["status"] == "running"
    finally:
        client.delete(location)


def test_cancel_takes_effect_queued_and_running_and_frees_the_worker(client: httpx.Client) -> None:
    running = client.post("/infer-preconditions", json=slow_model_body(seed=140), params={"wait": 0})
    queued = client.post("/infer-preconditions", json=slow_model_body(seed=141), params={"wait": 0})
    running_at, queued_at = running.headers["Location"], queued.headers["Location"]
    try:
        wait_until(lambda: client.get(running_at).json()["status"] == "running", 20, "the model job to start")
        assert client.get(queued_at).json()["status"] == "queued"  # the worker runs one model job at a time
        answer = client.delete(queued_at)
        assert answer.status_code == 200 and answer.json()["status"] == "cancelled", answer.text
        assert client.get(queued_at).json()["status"] == "cancelled"
        again = client.post("/infer-preconditions", json=slow_model_body(seed=141), params={"wait": 0})
        assert again.status_code == 202 and again.json()["status"] == "queued"  # a new request runs it again
        assert client.delete(queued_at).json()["status"] == "cancelled"

        client.delete(running_at)
        wait_until(lambda: client.get(running_at).json()["status"] == "cancelled", 30, "the running job to stop")
    finally:
        client.delete(queued_at)
        client.delete(running_at)
    small = slow_model_body(seed=142)
    small["options"].update(samples_per_prompt=1, prompts_per_action=1, max_new_tokens=4)
    answer = client.post("/infer-preconditions", json=small, params={"wait": 60})
    assert answer.status_code == 200, answer.text  # the worker is free for the next job
