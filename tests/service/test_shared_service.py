"""One tenant must not take the shared service from the others (the attacks of docs/security.md).

Each test is an attack of one class on a real stack (Redis, the gateway, a worker with the real engine and
sandbox), from a tenant with a key of its own; each failed on the code before the fix. None of them depends on
the uid (they attack the gateway's and the worker's own code, not the sandbox's kernel boundary, which
tests/sandbox/test_boundary.py attacks as root and as `nobody`). Latencies under attack are measured by
`python bench/service_bench.py --attacks`, never asserted here.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from precond.stack import harness
from precond.stack.attacks import (
    POISON_BODY,
    SLEEPING_HISTORY,
    deep_demonstration,
    oversized_set_body,
    unknown_fields_body,
)
from precond.stack.keyed import KeyedStack, keyed_stack
from precond.stack.local import DEMOS, RULES, SPEC, Stack, check_body, infer_body, make_stack, serving, wait_until

TENANTS = ("attacker-corp", "victim-corp", "prober-corp", "filler-corp")
SET_BYTES_PER_TENANT = 60_000


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[KeyedStack]:
    with keyed_stack(
        tmp_path_factory.mktemp("shared"), tiny_model_dir, TENANTS, workers=1,
        PRECOND_TENANT_RATE_PER_S="20", PRECOND_TENANT_BURST="30",
        PRECOND_MAX_SET_BYTES_PER_TENANT=str(SET_BYTES_PER_TENANT), PRECOND_MAX_BODY_BYTES="4194304",
    ) as keyed:
        with keyed.stack.http() as http:  # the worker loads its model first (a start that holds its event loop)
            wait_until(lambda: http.get("/ready").status_code == 200, 60, "the worker's model to load")
        yield keyed


def client(keyed: KeyedStack, tenant: str | None, timeout: float = 60) -> httpx.Client:
    headers = {} if tenant is None else {"Authorization": f"Bearer {keyed.keys[tenant]}"}
    return httpx.Client(base_url=keyed.url, headers=headers, timeout=timeout)


# ---- class 1: a request that parses but crashes the gateway's checks ---------------------------------------


def test_a_deeply_nested_demonstration_is_a_422_not_a_500(keyed: KeyedStack) -> None:
    with client(keyed, "attacker-corp") as http:
        inferred = http.post("/infer-preconditions", json=infer_body(demonstrations=[deep_demonstration()]))
        created = http.post("/precondition-sets", json={"spec": SPEC, "preconditions": RULES,
                                                        "demonstrations": [DEMOS[0]]})
        assert created.status_code == 201, created.text
        more = {"demonstrations": [deep_demonstration()], "options": {"generators": ["enumerate"]}}
        reinferred = http.post(f"/precondition-sets/{created.json()['id']}/reinfer", json=more)
    for answer in (inferred, reinferred):
        assert answer.status_code == 422, answer.text
        error = answer.json()["error"]
        assert error["field"].startswith("demonstrations") and "nested too deeply" in error["message"], error


def test_many_unknown_fields_cost_one_error_not_the_gateways_memory(keyed: KeyedStack) -> None:
    raw = unknown_fields_body()
    assert len(raw) < 4_194_304
    pid = harness.gateway_pid(keyed.stack)
    before = harness.rss_kib(pid)
    with client(keyed, "attacker-corp") as http:
        answer = http.post("/infer-preconditions", content=raw, headers={"Content-Type": "application/json"})
    grown_mib = (harness.rss_kib(pid) - before) / 1024
    assert answer.status_code == 422, answer.text
    assert "more than 100,000 JSON values" in answer.json()["error"]["message"], answer.text
    assert grown_mib < 150, f"the gateway grew by {grown_mib:.0f} MiB for one request"


def test_a_large_body_that_is_not_json_says_where(keyed: KeyedStack) -> None:
    """Parsed in the check pool (over 64 KiB), and answered as the event loop's parse answers a small one."""
    raw = httpx.Request("POST", "/", json=infer_body(spec=SPEC + "#" * 100_000)).content[:-1] + b",}"
    with client(keyed, "attacker-corp") as http:
        answer = http.post("/infer-preconditions", content=raw, headers={"Content-Type": "application/json"})
    error = answer.json()["error"]
    assert answer.status_code == 422 and error["field"] == "body", answer.text
    assert error["message"].startswith("body is not valid JSON") and "line 1, column" in error["message"], error


# ---- class 2: limits before work -------------------------------------------------------------------------


def test_a_set_over_its_size_is_refused_before_its_demonstrations_are_parsed(keyed: KeyedStack) -> None:
    """3.8 MB of demonstrations, the last one broken: the size bound answers (413) before any parse (a 422
    for the broken one would mean every demonstration was parsed first, on the gateway's event loop)."""
    with client(keyed, "attacker-corp") as http:
        answer = http.post("/precondition-sets", json=oversized_set_body())
    assert answer.status_code == 413, answer.text
    assert "PRECOND_MAX_SET_BYTES" in answer.json()["error"]["message"]


# ---- class 3: who the other tenants are, without a key -----------------------------------------------------


def test_metrics_without_a_key_name_no_tenant(keyed: KeyedStack) -> None:
    with client(keyed, "victim-corp") as http:
        assert http.post("/check-actions", json=check_body()).status_code == 200
        http.post("/infer-preconditions", json=infer_body(demonstrations=[deep_demonstration()]))
    with client(keyed, None) as http:
        metrics = http.get("/metrics")
    assert metrics.status_code == 200 and "precond_http_requests" in metrics.text
    leaked = [tenant for tenant in TENANTS if tenant in metrics.text]
    assert leaked == [], leaked


@pytest.fixture
def redis_down(tmp_path: Path, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(tmp_path, tiny_model_dir)
    with serving(stack, workers=0):
        stack.redis.stop()
        yield stack


def test_ready_with_redis_down_does_not_show_where_redis_is(redis_down: Stack) -> None:
    with redis_down.http() as http:
        answers = [http.get("/ready"), http.post("/check-actions", json=check_body())]
    for answer in answers:
        assert answer.status_code == 503, answer.text
        assert str(redis_down.redis.port) not in answer.text and "127.0.0.1" not in answer.text, answer.text


# ---- class 4: stored sets fill the shared queue Redis -------------------------------------------------------


def test_a_tenants_stored_sets_are_bounded_in_bytes_and_others_still_store(keyed: KeyedStack) -> None:
    body = {"spec": SPEC, "preconditions": RULES, "demonstrations": [DEMOS[0] * 20, DEMOS[1] * 20]}  # ~28 KB a set
    with client(keyed, "filler-corp") as http:
        codes = [http.post("/precondition-sets", json=body) for _ in range(5)]
    refused = [a for a in codes if a.status_code != 201]
    assert refused and refused[0].status_code == 422, [a.status_code for a in codes]
    error = refused[0].json()["error"]
    assert error["type"] == "sets_limited" and "PRECOND_MAX_SET_BYTES_PER_TENANT" in error["message"], error
    with client(keyed, "victim-corp") as http:
        assert http.post("/precondition-sets", json=body).status_code == 201


# ---- class 5: starvation by waiting -----------------------------------------------------------------------

def test_a_tenants_waiting_checks_leave_slots_for_the_others(keyed: KeyedStack) -> None:
    """Six checks that only wait, from one tenant, and once they hold what they can, another tenant's check: it
    is answered while all six still wait (before, they held every check slot and it waited for them to end)."""
    with client(keyed, "attacker-corp") as http:
        slow = []
        for seed in range(6):
            body = check_body(f"system.REQUEST('slow{seed}')")
            body["history"] = SLEEPING_HISTORY
            answer = http.post("/check-actions", json=body, params={"wait": 0})
            assert answer.status_code == 202, answer.text
            slow.append(answer.headers["X-Job-Id"])

        def states() -> list[str]:
            return [http.get(f"/jobs/{job_id}").json()["status"] for job_id in slow]

        queue = keyed.stack.redis.client()
        running = [f"arq:in-progress:{job_id}" for job_id in slow]
        wait_until(lambda: queue.exists(*running) >= 2, 10, "the slow checks to start")
        time.sleep(1)  # time for a worker without a share to start all it can
        with client(keyed, "victim-corp") as victim:
            answered = victim.post("/check-actions", json=check_body("system.REQUEST('time')"), params={"wait": 30})
        after = states()
    assert answered.status_code == 200, answered.text
    assert set(after) <= {"queued", "running"}, after


# ---- class 6: a poison job ---------------------------------------------------------------------------------

def test_a_poison_job_does_not_kill_its_worker(keyed: KeyedStack) -> None:
    """449 bytes that made the worker build 4^14 argument lists; the test stops the worker at 1 GiB (what
    the old code passed in about a second) rather than let it take the machine."""
    stack = keyed.stack
    (pid,) = stack.worker_pids()
    peak, stop = [0], threading.Event()

    def guard() -> None:
        while not stop.wait(0.05):
            peak[0] = max(peak[0], harness.tree_rss_kib(pid))
            if peak[0] > 1024 * 1024:
                harness.sigkill(pid)
                return

    watcher = threading.Thread(target=guard, daemon=True)
    watcher.start()
    try:
        with client(keyed, "attacker-corp", timeout=120) as http:
            answer = http.post("/infer-preconditions", json=POISON_BODY, params={"wait": 60})
    finally:
        stop.set()
        watcher.join()
    assert harness.alive(pid), f"the worker died (peak {peak[0] // 1024} MiB)"
    assert answer.status_code == 200, answer.text
    assert peak[0] < 1024 * 1024


# ---- class 7: rate limits on every route, failed authentications per source -------------------------------


def test_every_route_is_rate_limited(keyed: KeyedStack) -> None:
    with client(keyed, "prober-corp") as http:
        job_polls = [http.get("/jobs/nothing-here").status_code for _ in range(60)]
        set_reads = [http.get("/precondition-sets/nothing-here").status_code for _ in range(60)]
    with client(keyed, None) as http:  # the open routes, per source address
        health = [http.get("/health").status_code for _ in range(300)]
    assert 429 in job_polls and 429 in set_reads and 429 in health, (job_polls, set_reads, health)


@pytest.fixture
def guessed(tmp_path: Path, tiny_model_dir: Path) -> Iterator[KeyedStack]:
    with keyed_stack(tmp_path, tiny_model_dir, ("acme",), workers=0) as keyed:
        yield keyed


def test_failed_authentications_are_throttled_per_source(guessed: KeyedStack) -> None:
    with httpx.Client(base_url=guessed.url, timeout=30) as http:
        answers = [http.get("/jobs/x", headers={"Authorization": f"Bearer pk_guess{i}"}) for i in range(300)]
    codes = [a.status_code for a in answers]
    assert codes.count(401) <= 40 and 429 in codes, codes
    throttled = next(a for a in answers if a.status_code == 429)
    assert throttled.json()["error"]["type"] == "auth_limited" and int(throttled.headers["Retry-After"]) >= 1
