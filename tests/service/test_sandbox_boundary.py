"""The sandbox boundary over HTTP, on a real stack: a forging precondition cannot turn a refusal into
"allowed", a worker's secrets never reach an error message, and a worker that cannot confine untrusted
code takes no job, says why on /ready, and loses nothing (the job runs once a confined worker comes)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.stack.hostile_corpus import FIND
from precond.stack.local import ROOT, Stack, check_body, make_stack, serving, wait_until

SECRET = "hunter2-not-for-callers"
FORGE = ("[typing.sys.modules['builtins'].setattr(m, '_verdict', lambda *a: {'allowed': True, 'violations': [], "
         "'error': None}) for m in [typing.sys.modules.get('__main__'), "
         "typing.sys.modules.get('precond.sandbox.child.check')] "
         "if m is not None] == []")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("boundary"), tiny_model_dir, PRECOND_TEST_SECRET=SECRET,
                       PRECOND_WORKER_SECRET_URL=f"redis://:{SECRET}@127.0.0.1:1/0")
    with serving(stack, workers=1):
        yield stack


def forged_body() -> dict[str, Any]:
    body = check_body("system.FindRestaurants()", "system.FindRestaurants()")
    body["spec"] = "import typing\n" + body["spec"]
    body["preconditions"] = {"SYSTEM.FindRestaurants": [FORGE, "self.user.informed_slot['cuisine']"]}
    return body


def test_a_forging_precondition_cannot_allow_a_forbidden_call(stack: Stack) -> None:
    with stack.http() as client:
        answer = client.post("/check-actions", json=forged_body(), params={"wait": 30})
    assert answer.status_code == 200, answer.text
    verdicts = answer.json()["results"]
    assert [v["allowed"] for v in verdicts] == [False, False], verdicts


def test_worker_secrets_never_reach_an_error(stack: Stack) -> None:
    body = check_body()
    leak = "str(dict(find('environ'))) + repr(find('open')('/proc/self/environ').read())"
    body["history"] = FIND + f"raise ValueError({leak})\n"
    with stack.http() as client:
        answer = client.post("/check-actions", json=body, params={"wait": 30})
    assert answer.status_code == 422, answer.text
    assert SECRET not in answer.text
    assert "Operation not permitted" in answer.text


@pytest.fixture
def unconfinable(tmp_path: Path, tiny_model_dir: Path) -> Iterator[Stack]:
    """A worker whose seccomp binding cannot load (as on a host without libseccomp)."""
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "pyseccomp.py").write_text("raise ImportError('libseccomp.so.2: cannot open shared object file')\n")
    stack = make_stack(tmp_path, tiny_model_dir, PYTHONPATH=f"{broken}:{ROOT}")
    with serving(stack, workers=1):
        yield stack


def test_a_worker_that_cannot_confine_takes_no_job_and_says_why(unconfinable: Stack) -> None:
    (beat,) = unconfinable.heartbeats()
    assert beat["sandbox"] == "unavailable" and "libseccomp" in str(beat["sandbox_error"])
    with unconfinable.http() as client:
        ready = client.get("/ready")
        assert ready.status_code == 503 and "confine" in ready.text and "libseccomp" in ready.text
        accepted = client.post("/check-actions", json=check_body(), params={"wait": 1})
        assert accepted.status_code == 202, accepted.text
        job = accepted.headers["Location"]
        assert client.get(job).json()["status"] == "queued"
        unconfinable.env["PYTHONPATH"] = str(ROOT)  # a worker that can confine: the job was never lost
        unconfinable.start_worker()
        wait_until(lambda: client.get(job).json()["status"] == "succeeded", 60, "the queued job")


def test_health_says_whether_untrusted_code_runs_confined(stack: Stack) -> None:
    with httpx.Client(base_url=stack.base_url) as client:
        assert client.get("/health").json()["sandbox"] == "confined"


def test_a_limit_failure_is_never_reused_as_the_requests_result(stack: Stack) -> None:
    body = check_body()
    body["history"] += "print('x' * 10_000_000)\n"  # over the output limit: the call fails on a limit
    started = _jobs_started(stack)
    with stack.http() as client:
        first = client.post("/check-actions", json=body, params={"wait": 30})
        second = client.post("/check-actions", json=body, params={"wait": 30})
    assert first.status_code == second.status_code == 422
    assert first.json()["error"]["type"] == "resource_limit" and "output" in first.json()["error"]["message"]
    assert _jobs_started(stack) - started == 2  # the identical retry ran again instead of reading the failure


def _jobs_started(stack: Stack) -> int:
    return sum(int(str(beat["jobs_started"])) for beat in stack.heartbeats())
