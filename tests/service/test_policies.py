"""Trained policies over the API on a real stack (Redis, gateway, one worker with the tiny model): a tenant
trains one (a job on the training queue), lists it, asks for next actions with it and deletes it; another
tenant can do none of that with it, not even by forging a job; bad requests are refused naming the field; a
cancelled training stores nothing. The tiny random model stands in for the real one: what is asserted is
the plumbing and the refusals (the quality is docs/results.md's)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.jobs.queue import keys as job_keys
from precond.jobs.queue.keys import JOB_PREFIX, MODEL_QUEUE, RESULT_PREFIX, tenant_tag, wake_channel
from precond.jobs.queue.payloads import decode_end, encode_job
from precond.stack.local import DEMOS, SPEC, Stack, example, make_stack, serving, wait_until
from tests.service.test_tenants import SECRET, make_key

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    path = tmp_path_factory.mktemp("keys") / "keys.jsonl"
    return path, {tenant: make_key(path, tenant)[1] for tenant in ("acme", "globex", "small")}


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path,
          keys: tuple[Path, dict[str, str]]) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("policies"), tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys[0]),
                       PRECOND_MAX_TRAINING_STEPS="300", PRECOND_MAX_POLICIES_PER_TENANT="2",
                       PRECOND_MAX_POLICY_VERSIONS="2", PRECOND_JOB_TIMEOUT_S="300",
                       PRECOND_WAIT_MAX_S="120")  # the trainings' `?wait=120` waits that long on a busy machine
    with serving(stack, workers=1):
        yield stack


def training(steps: int = 2, demos: list[str] | None = None, **options: Any) -> dict[str, Any]:
    return {"spec": SPEC, "demonstrations": demos or DEMOS[:2],
            "options": {"steps": steps, "max_tokens": 1024, **options}}


def trained(client: httpx.Client, body: dict[str, Any] | None = None, path: str = "/policies") -> dict[str, Any]:
    answer = client.post(path, json=body or training(), params={"wait": 120}, timeout=150)
    assert answer.status_code == 200, answer.text
    result: dict[str, Any] = answer.json()
    return result


def next_action(client: httpx.Client, policy: str | None) -> httpx.Response:
    body = example("next-action")
    body["options"] = {"policy": policy} if policy else {}
    return client.post("/next-action", json=body, params={"wait": 120}, timeout=150)


def test_a_tenant_trains_a_policy_asks_with_it_retrains_it_and_deletes_it(acme: httpx.Client) -> None:
    first = trained(acme)
    adapter_id = first["id"]
    assert adapter_id.startswith("ad_") and first["version"] == 1 and first["reference"] == f"{adapter_id}@1"
    assert first["result"]["steps"] == 2 and first["result"]["examples"] == 2 and first["result"]["calls"]
    assert acme.get(f"/policies/{adapter_id}").json() == first
    listed = acme.get("/policies").json()
    assert [a["id"] for a in listed["adapters"]] == [adapter_id] and listed["bytes"] > first["result"]["adapter_bytes"]

    base = next_action(acme, None)
    tuned = next_action(acme, f"adapter:{adapter_id}")
    assert base.status_code == 200 and tuned.status_code == 200, (base.text, tuned.text)
    assert base.json()["model"]["adapter"] is None
    assert tuned.json()["model"]["adapter"].startswith(f"{adapter_id}-v1@")

    second = trained(acme, training(steps=3), f"/policies/{adapter_id}/versions")
    assert (second["id"], second["version"], second["result"]["steps"]) == (adapter_id, 2, 3)
    latest = next_action(acme, f"adapter:{adapter_id}")
    pinned = next_action(acme, f"adapter:{adapter_id}@1")
    assert latest.json()["model"]["adapter"].startswith(f"{adapter_id}-v2@")
    assert pinned.json()["model"]["adapter"] == tuned.json()["model"]["adapter"]
    assert acme.get(f"/policies/{adapter_id}@1").json() == first  # versions are never rewritten
    over = acme.post(f"/policies/{adapter_id}/versions", json=training())
    assert over.status_code == 422 and "PRECOND_MAX_POLICY_VERSIONS" in over.json()["error"]["message"]

    assert acme.delete(f"/policies/{adapter_id}").status_code == 204
    assert acme.get(f"/policies/{adapter_id}").status_code == 404
    gone = next_action(acme, f"adapter:{adapter_id}")
    assert gone.status_code == 404 and gone.json()["error"]["field"] == "options.policy"
    assert acme.get("/policies").json() == {"adapters": [], "bytes": 0}  # every version's bytes given back


def test_another_tenants_policy_is_not_found_anywhere(acme: httpx.Client, globex: httpx.Client) -> None:
    adapter_id = trained(acme)["id"]
    try:
        mine = acme.get(f"/policies/{adapter_id}")
        for answer in (globex.get(f"/policies/{adapter_id}"), globex.get(f"/policies/{adapter_id}@1"),
                       globex.post(f"/policies/{adapter_id}/versions", json=training()),
                       globex.delete(f"/policies/{adapter_id}"),
                       next_action(globex, f"adapter:{adapter_id}")):
            assert answer.status_code == 404, answer.text
        missing = globex.get("/policies/ad_" + "0" * 24).json()["error"]["message"]
        found = globex.get(f"/policies/{adapter_id}").json()["error"]["message"]
        assert found == missing.replace("0" * 24, adapter_id[3:])  # word for word as one that does not exist
        assert globex.get("/policies").json() == {"adapters": [], "bytes": 0}
        assert acme.get(f"/policies/{adapter_id}").json() == mine.json()  # untouched by the attempts
    finally:
        acme.delete(f"/policies/{adapter_id}")


def test_a_forged_job_cannot_reach_another_tenants_adapter(stack: Stack, acme: httpx.Client) -> None:
    """The worker reads the adapter under the tag of the job's owner, whatever the payload names: a job of
    globex's that names acme's adapter (enqueued straight into Redis, past the gateway) fails as not found."""
    adapter = trained(acme)
    try:
        body = example("next-action")
        body["options"] = {"policy": f"adapter:{adapter['reference']}"}
        globex = tenant_tag(SECRET, "globex")
        job_id = job_keys.job_id("next-action", body, None, SECRET, globex)

        redis = stack.redis.client()
        redis.set(JOB_PREFIX + job_id, encode_job("next-action", body, job_id, 1), px=600_000)
        redis.zadd(MODEL_QUEUE, {job_id: 1})
        redis.publish(wake_channel(MODEL_QUEUE), b"1")
        wait_until(lambda: redis.exists(RESULT_PREFIX + job_id), 120, "the forged job's end")
        outcome = decode_end(redis.get(RESULT_PREFIX + job_id) or b"").outcome
        assert outcome is not None and outcome.status == "failed" and outcome.error is not None, outcome
        assert outcome.error.type == "not_found" and outcome.error.field == "options.policy"
    finally:
        acme.delete(f"/policies/{adapter['id']}")


def test_bad_requests_are_refused_naming_the_field(acme: httpx.Client) -> None:
    no_actions = training(demos=["user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\n"])
    cases = [
        (training(steps=301), 422, "options.steps", "PRECOND_MAX_TRAINING_STEPS"),
        (training(steps=401), 422, "options.steps", "400"),
        (no_actions, 422, "demonstrations", "nothing to train on"),
        (training(rank=64), 422, "options.rank", "32"),
    ]
    for body, status, field, words in cases:
        answer = acme.post("/policies", json=body, params={"wait": 30})
        assert answer.status_code == status, answer.text
        assert answer.json()["error"]["field"] == field and words in answer.json()["error"]["message"], answer.text
    for policy, status in (("ad_123", 422), ("adapter:ad_" + "g" * 24, 422), ("adapter:ad_" + "1" * 24, 404),
                           ("adapter:ad_" + "1" * 24 + "@0", 422)):
        answer = next_action(acme, policy)
        assert answer.status_code == status, answer.text
        assert answer.json()["error"]["field"] == "options.policy", answer.text
    assert acme.get("/policies").json()["adapters"] == []


def trainings(worker: int) -> set[int]:
    """The worker's child processes that train (the others are its sandbox's servers)."""
    found = set()
    for entry in Path("/proc").iterdir():
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if parent == worker and b"precond.worker.training_process" in command:
            found.add(int(entry.name))
    return found


def test_a_training_runs_in_a_child_of_the_worker_and_a_cancelled_one_stores_nothing(
    stack: Stack, acme: httpx.Client
) -> None:
    """The worker never holds the trainable model: the training runs in a process of its own, which a
    cancellation ends."""
    [worker] = stack.worker_pids()
    started = acme.post("/policies", json=training(steps=300, demos=DEMOS), params={"wait": 0})
    assert started.status_code == 202, started.text
    job = started.json()["id"]
    deadline = time.monotonic() + 60
    while acme.get(f"/jobs/{job}").json()["progress"]["phase"] != "train":
        assert time.monotonic() < deadline, "the training never started"
        time.sleep(0.05)
    children = trainings(worker)
    assert len(children) == 1 and worker not in children
    assert acme.delete(f"/jobs/{job}").json()["status"] == "cancelled"
    time.sleep(1)
    assert not trainings(worker) and not any(Path(f"/proc/{pid}").exists() for pid in children)
    assert acme.get("/policies").json() == {"adapters": [], "bytes": 0}
    assert not stack.redis.client().keys("precond:policy:*")


def test_a_tenant_at_its_bound_of_policies_is_refused(acme: httpx.Client) -> None:
    made = [trained(acme)["id"] for _ in range(2)]
    try:
        answer = acme.post("/policies", json=training())
        assert answer.status_code == 422 and "PRECOND_MAX_POLICIES_PER_TENANT" in answer.json()["error"]["message"]
    finally:
        for adapter_id in made:
            acme.delete(f"/policies/{adapter_id}")
