"""Tenants on a real stack: API keys (401s, revocation without restart), job ownership (another tenant's job
is a 404), per-tenant caching, quotas (429 naming the limit), the work budget (422 before queueing), and
fair ordering of the queue. Only the gateway runs for most of these: queued jobs stay queued, so the
tests assert what is in Redis, never how long anything took."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import pytest

from precond.cli.serve_commands import open_tenant_note
from precond.gateway.api_keys import KeyRecord, digest, new_key, read_records, write_records
from precond.gateway.settings import GatewaySettings
from precond.jobs.queue.keys import CHECK_QUEUE, MODEL_QUEUE, JobId, tenant_tag, worker_key
from precond.stack.local import ROOT, Stack, check_body, infer_body, make_stack, serving

SECRET = b"stack-secret-for-tests"


def make_key(path: Path, tenant: str, **changes: object) -> tuple[str, str]:
    key_id, key = new_key()
    record = replace(KeyRecord(key_id, tenant, digest(key), datetime.now(UTC).isoformat()), **changes)
    write_records(path, [*(read_records(path) if path.exists() else []), record])
    return key_id, key


@pytest.fixture(scope="module")
def keys_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("keys") / "keys.jsonl"


@pytest.fixture(scope="module")
def keys(keys_file: Path) -> dict[str, str]:
    return {tenant: make_key(keys_file, tenant)[1] for tenant in ("acme", "globex", "flood", "busy", "newcomer")}


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path, keys_file: Path,
          keys: dict[str, str]) -> Iterator[Stack]:
    stack = make_stack(
        tmp_path_factory.mktemp("tenants"), tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys_file),
        PRECOND_TENANT_MAX_JOBS="4", PRECOND_TENANT_RATE_PER_S="1000", PRECOND_TENANT_BURST="1000",
        PRECOND_QUEUE_MAX_JOBS="100", PRECOND_MAX_WORK_POINTS="50000",
    )
    with serving(stack, workers=0):  # no worker: what is queued stays queued
        yield stack


def client_for(stack: Stack, key: str | None) -> httpx.Client:
    headers = {} if key is None else {"Authorization": f"Bearer {key}"}
    return httpx.Client(base_url=stack.base_url, headers=headers, timeout=30)


def queued(stack: Stack, seed: int, key: str) -> str:
    body = check_body(f"system.REQUEST('c{seed}')")
    with client_for(stack, key) as client:
        answer = client.post("/check-actions", json=body, params={"wait": 0})
    assert answer.status_code == 202, answer.text
    return str(answer.headers["X-Job-Id"])


def test_every_operation_needs_a_key_and_says_what_is_wrong(stack: Stack, keys_file: Path) -> None:
    with client_for(stack, None) as anonymous:
        missing = anonymous.post("/check-actions", json=check_body())
        assert missing.status_code == 401 and "missing API key" in missing.json()["error"]["message"]
        assert missing.headers["WWW-Authenticate"] == "Bearer"
        assert anonymous.get("/jobs/check-" + "0" * 16 + "-" + "0" * 48).status_code == 401
        for open_path in ("/health", "/metrics"):
            assert anonymous.get(open_path).status_code == 200
    with client_for(stack, "pk_not-a-key") as wrong:
        assert wrong.post("/check-actions", json=check_body()).json()["error"] == {
            "type": "unauthorized", "message": "unknown API key"}
    _, expired = make_key(keys_file, "acme", expires=(datetime.now(UTC) - timedelta(days=1)).isoformat())
    with client_for(stack, expired) as late:
        answer = late.post("/check-actions", json=check_body())
        assert answer.status_code == 401 and "expired" in answer.json()["error"]["message"]


def test_a_revoked_key_stops_working_without_a_restart(stack: Stack, keys_file: Path) -> None:
    key_id, key = make_key(keys_file, "acme")
    with client_for(stack, key) as client:
        assert client.get("/jobs/" + queued(stack, 100, key)).status_code == 200
        done = subprocess.run([sys.executable, "-m", "precond.cli", "keys", "revoke", key_id, "--file", str(keys_file)],
                              cwd=ROOT, capture_output=True, text=True, check=False)
        assert done.returncode == 0, done.stderr
        answer = client.post("/check-actions", json=check_body())
        assert answer.status_code == 401 and f"{key_id} was revoked" in answer.json()["error"]["message"]


def test_another_tenants_job_is_not_found(stack: Stack, keys: dict[str, str]) -> None:
    job = queued(stack, 1, keys["acme"])
    assert JobId.parse(job).tenant == tenant_tag(SECRET, "acme")
    with client_for(stack, keys["globex"]) as other:
        for method in ("GET", "DELETE"):
            answer = other.request(method, f"/jobs/{job}")
            assert answer.status_code == 404
            assert answer.json()["error"] == {"type": "not_found", "message": f"no job {job}"}
    with client_for(stack, keys["acme"]) as owner:
        assert owner.get(f"/jobs/{job}").json()["status"] == "queued"
        assert owner.delete(f"/jobs/{job}").status_code == 200


def test_identical_requests_of_two_tenants_are_two_jobs(stack: Stack, keys: dict[str, str]) -> None:
    assert queued(stack, 2, keys["acme"]) != queued(stack, 2, keys["globex"])
    assert queued(stack, 2, keys["acme"]) == queued(stack, 2, keys["acme"])  # one tenant's twins share a job


def test_jobs_over_the_tenants_cap_are_429_and_other_tenants_go_on(stack: Stack, keys: dict[str, str]) -> None:
    client = stack.redis.client()
    client.delete(f"precond:tenant:{tenant_tag(SECRET, 'flood')}:jobs")
    for seed in range(10, 14):
        queued(stack, seed, keys["flood"])
    with client_for(stack, keys["flood"]) as flood:
        answer = flood.post("/check-actions", json=check_body("system.REQUEST('c14')"), params={"wait": 0})
    assert answer.status_code == 429
    error = answer.json()["error"]
    assert error["type"] == "jobs_limited" and "'flood' has 4 jobs queued or running" in error["message"]
    assert int(answer.headers["Retry-After"]) >= 1
    queued(stack, 14, keys["globex"])


def test_the_queue_serves_tenants_fairly(stack: Stack, keys: dict[str, str]) -> None:
    busy = [queued(stack, seed, keys["busy"]) for seed in range(20, 24)]
    single = queued(stack, 30, keys["newcomer"])
    order = [m.decode() for m in stack.redis.client().zrange(CHECK_QUEUE, 0, -1)]  # arq serves in this order
    # the newcomer's one job, sent after all of the busy tenant's, is served before all but the first of them
    assert order.index(single) < order.index(busy[1]) < order.index(busy[2]) < order.index(busy[3])


def test_a_request_over_the_work_budget_is_422_before_queueing(stack: Stack, keys: dict[str, str]) -> None:
    demo = "user = USER()\nsystem = SYSTEM(user)\n" + "".join(f"system.REQUEST('s{i}')\n" for i in range(400))
    body = infer_body(demonstrations=[demo])
    with client_for(stack, keys["acme"]) as client:
        before = stack.redis.client().zcard(MODEL_QUEUE)
        answer = client.post("/infer-preconditions", json=body, params={"wait": 0})
        assert stack.redis.client().zcard(MODEL_QUEUE) == before
    assert answer.status_code == 422
    error = answer.json()["error"]
    assert error["field"] == "demonstrations" and "PRECOND_MAX_WORK_POINTS" in error["message"]


def test_declared_size_limits_are_enforced(stack: Stack, keys: dict[str, str]) -> None:
    body = check_body()
    body["preconditions"] = {"SYSTEM.INFORM": ["self.user.no_more"] * 33}
    with client_for(stack, keys["acme"]) as client:
        answer = client.post("/check-actions", json=body)
    assert answer.status_code == 422
    assert answer.json()["error"]["field"].startswith("preconditions.SYSTEM.INFORM")


@pytest.fixture
def rate_limited(tmp_path: Path, tiny_model_dir: Path) -> Iterator[tuple[Stack, str]]:
    keys_file = tmp_path / "keys.jsonl"
    _, key = make_key(keys_file, "acme")
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys_file),
                       PRECOND_TENANT_RATE_PER_S="0.01", PRECOND_TENANT_BURST="3")
    with serving(stack, workers=0):
        yield stack, key


def test_a_tenant_over_its_rate_is_429_naming_the_limit(rate_limited: tuple[Stack, str]) -> None:
    stack, key = rate_limited
    with client_for(stack, key) as client:
        codes = [client.post("/check-actions", json=check_body(f"system.REQUEST('r{i}')"),
                             params={"wait": 0}).status_code for i in range(3)]
        answer = client.post("/check-actions", json=check_body())
    assert codes == [202, 202, 202]
    assert answer.status_code == 429 and answer.json()["error"]["type"] == "rate_limited"
    assert "0.01 requests/s" in answer.json()["error"]["message"] and int(answer.headers["Retry-After"]) >= 1


def test_serve_refuses_an_open_non_loopback_address() -> None:
    done = subprocess.run([sys.executable, "-m", "precond.cli", "serve", "--host", "0.0.0.0"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60, check=False,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)})
    assert done.returncode == 2
    assert "without API keys" in done.stderr and "--no-auth" in done.stderr


@pytest.mark.stack
@pytest.mark.parametrize("lifted", [False, True])
def test_the_open_tenant_keeps_the_rate_unless_lifted_for_local_use(tmp_path: Path, tiny_model_dir: Path,
                                                                    lifted: bool) -> None:
    """Without keys every caller is the tenant `public`: held to the tenants' rate, unless
    PRECOND_PUBLIC_RATE_LIMIT is off (`precond serve --no-rate-limit`)."""
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_TENANT_RATE_PER_S="0.01", PRECOND_TENANT_BURST="3",
                       PRECOND_PUBLIC_RATE_LIMIT=str(not lifted).lower())
    with serving(stack, workers=0), stack.http() as client:
        codes = [client.post("/check-actions", json=check_body(f"system.REQUEST('r{i}')"),
                             params={"wait": 0}).status_code for i in range(8)]
    assert codes == [202] * 8 if lifted else codes == [202] * 3 + [429] * 5


@pytest.mark.parametrize(("args", "says"), [
    (["--host", "0.0.0.0", "--no-auth"], "for local use (a loopback address), not --host 0.0.0.0"),
    (["--keys"], "with PRECOND_API_KEYS_FILE every tenant keeps its rate"),
])
def test_serve_lifts_only_the_open_local_tenants_rate(tmp_path: Path, args: list[str], says: str) -> None:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)}
    if args == ["--keys"]:
        make_key(tmp_path / "keys.jsonl", "acme")
        env["PRECOND_API_KEYS_FILE"], args = str(tmp_path / "keys.jsonl"), []
    done = subprocess.run([sys.executable, "-m", "precond.cli", "serve", "--no-rate-limit", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=60, check=False, env=env)
    assert done.returncode == 2 and says in done.stderr, done.stderr


def test_the_ready_line_says_what_the_open_tenant_may_do(tmp_path: Path) -> None:
    open_service = GatewaySettings(tenant_rate_per_s=50, tenant_burst=100, tenant_max_jobs=32)
    assert open_tenant_note(open_service, lifted=False) == (
        "; no API keys: every caller is the tenant 'public', 50 requests/s (bursts of 100), 32 jobs at once "
        "(--no-rate-limit lifts the rate)")
    assert open_tenant_note(open_service, lifted=True) == (
        "; no API keys: every caller is the tenant 'public', at any request rate, 32 jobs at once")
    assert open_tenant_note(GatewaySettings(api_keys_file=tmp_path / "keys.jsonl"), lifted=False) == ""


@pytest.fixture
def small_answers(tmp_path: Path, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_MAX_RESPONSE_BYTES="1024")
    with serving(stack, workers=1):
        yield stack


def test_an_answer_over_the_response_bound_is_refused_with_its_size(small_answers: Stack) -> None:
    calls = [f"system.REQUEST('slot_{i}')" for i in range(40)]
    with small_answers.http() as client:
        answer = client.post("/check-actions", json=check_body(*calls), params={"wait": 30})
        assert answer.status_code == 422, answer.text
        error = answer.json()["error"]
        assert error["type"] == "response_too_large" and "PRECOND_MAX_RESPONSE_BYTES (1,024)" in error["message"]
        assert client.post("/check-actions", json=check_body(calls[0]), params={"wait": 30}).status_code == 200


def test_ready_tells_anybody_a_reason_code_and_only_an_operator_the_details(
    stack: Stack, keys_file: Path, keys: dict[str, str]
) -> None:
    """/ready answers without a key, so what it says is public: a worker's exception (its model directory, a
    memory limit, the CPU) reaches an operator's key and the log, never a tenant or a stranger."""
    _, operator = make_key(keys_file, "ops", operator=True)
    beat = ('{"id": "w-ready", "host": "h", "pid": 1, "queues": ["q"], "model_loaded": false, '
            '"sandbox": "unavailable", "sandbox_error": "missing CAP_SETUID in /srv/secret/models"}')
    redis = stack.redis.client()
    redis.set(worker_key("w-ready"), beat, px=60_000)
    try:
        for key in (None, keys["acme"], "pk_not-a-key"):
            with client_for(stack, key) as client:
                answer = client.get("/ready")
            assert answer.status_code == 503 and answer.json()["error"]["type"] == "sandbox_unavailable"
            assert "CAP_SETUID" not in answer.text and "/srv/secret" not in answer.text, answer.text
        with client_for(stack, operator) as client:
            answer = client.get("/ready")
        assert answer.status_code == 503 and answer.json()["error"]["type"] == "sandbox_unavailable"
        assert "missing CAP_SETUID in /srv/secret/models" in answer.json()["error"]["message"]
    finally:
        redis.delete(worker_key("w-ready"))
    with client_for(stack, None) as client:
        assert client.get("/ready").json()["error"]["type"] == "no_worker"
