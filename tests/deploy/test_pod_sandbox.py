"""The sandbox in the worker's pod, simulated here: the self-check (`precond sandbox-check`) and the attacks on
the boundary run as the pod's user and groups, with the capabilities and no_new_privs its securityContext
gives, under a seccomp profile like the runtime's default; a pod without what the sandbox needs is refused
with the reason, by the self-check, by the worker's readiness probe and by the gateways' /ready."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from manifests import ROOT, base, container, pod_spec

from precond.stack.identity import readable_sandbox_copy, runnable_python
from precond.stack.local import RedisServer, Stack, make_stack, serving, wait_until

pytestmark = pytest.mark.stack

HERE = Path(__file__).parent
ATTACKS = ROOT / "tests" / "sandbox" / "attack_probe.py"
HEALTHCHECK = ROOT / "docker" / "healthcheck.py"
root_only = pytest.mark.skipif(os.geteuid() != 0, reason="changing to the pod's user needs root")


def worker_pod() -> dict[str, Any]:
    """The worker's pod and container security contexts, merged as the kubelet applies them."""
    spec = pod_spec(base(), "Deployment", "precond-worker")
    return {**spec["securityContext"], **container(base(), "Deployment", "precond-worker")["securityContext"]}


def setpriv(context: dict[str, Any]) -> list[str]:
    """setpriv's options for a process started as `context` says (runAsUser, runAsGroup, fsGroup, dropped and
    added capabilities, allowPrivilegeEscalation)."""
    groups = [str(context["fsGroup"])] if "fsGroup" in context else []
    capabilities = context.get("capabilities", {})
    kept = "".join(f",+{name.lower()}" for name in capabilities.get("add", []))
    options = [f"--reuid={context['runAsUser']}", f"--regid={context['runAsGroup']}",
               f"--groups={','.join(groups)}" if groups else "--clear-groups"]
    if "ALL" in capabilities.get("drop", []):
        options += ["--inh-caps=-all", "--ambient-caps=-all", f"--bounding-set=-all{kept}"]
    if context.get("allowPrivilegeEscalation") is False:
        options.append("--no-new-privs")
    return options


@pytest.fixture(scope="module")
def readable_copy() -> Iterator[Path]:
    where = Path(tempfile.mkdtemp(prefix="pod-sandbox-", dir="/tmp"))
    try:
        yield readable_sandbox_copy(where, [ATTACKS, HERE / "runtime_profile.py"])
    finally:
        shutil.rmtree(where, ignore_errors=True)


def run_as(context: dict[str, Any], copy: Path, profile: str, *program: str) -> subprocess.CompletedProcess[str]:
    """`program` (a script in the copy) as `context`'s identity, under the seccomp `profile`."""
    options = setpriv(context)
    python = runnable_python(options)
    return subprocess.run(
        ["setpriv", *options, python, "runtime_profile.py", profile, python, *program],
        cwd=copy, env={"PYTHONPATH": str(copy), "PATH": "/usr/bin:/bin", "PRECOND_TEST_SECRET": "hunter2"},
        capture_output=True, text=True, timeout=180, check=False,
    )


def self_check(context: dict[str, Any], copy: Path, profile: str = "runtime-default") -> tuple[int, dict[str, Any]]:
    done = run_as(context, copy, profile, "-m", "precond.sandbox.selfcheck")
    assert done.stdout.strip(), done.stderr[-3000:]  # a report, never a traceback
    return done.returncode, json.loads(done.stdout)


@root_only
def test_the_worker_pod_confines_untrusted_code_without_any_capability(readable_copy: Path) -> None:
    pod = worker_pod()
    assert pod["capabilities"] == {"drop": ["ALL"]} and pod["runAsUser"] != 0
    code, report = self_check(pod, readable_copy)
    assert code == 0 and report["confined"] is True, report
    identity = report["identity"]
    assert identity["uid"] == pod["runAsUser"] and identity["gid"] == pod["runAsGroup"]
    assert int(identity["CapEff"], 16) == int(identity["CapPrm"], 16) == int(identity["CapBnd"], 16) == 0
    assert identity["NoNewPrivs"] == "1" and identity["Seccomp"] == "2"  # under the runtime's filter
    # the runtime's profile denies namespaces: the sandbox's optional empty network namespace is not made
    assert report["network_namespace"] is False

    attacks = run_as(pod, readable_copy, "runtime-default", "attack_probe.py")
    assert attacks.returncode == 0, attacks.stderr[-3000:]
    results = json.loads(attacks.stdout)
    assert results["uid"] == pod["runAsUser"]
    escaped = {name: outcome for name, outcome in results["results"].items() if not outcome.startswith("denied")}
    assert not escaped and len(results["results"]) >= 20
    assert "hunter2" not in attacks.stdout


@root_only
def test_a_pod_running_as_root_without_capabilities_is_refused(readable_copy: Path) -> None:
    """A pod that drops every capability but forgets runAsNonRoot: the children cannot drop from root to
    nobody, so nothing runs, and the report says which capabilities that would need."""
    pod = {**worker_pod(), "runAsUser": 0, "runAsGroup": 0}
    code, report = self_check(pod, readable_copy)
    assert code == 1 and report["confined"] is False
    assert "CAP_SETUID" in report["reason"] and report["identity"]["uid"] == 0


@root_only
def test_a_runtime_profile_that_forbids_seccomp_is_refused_with_its_reason(readable_copy: Path) -> None:
    """A custom seccomp profile without seccomp(): the filter cannot even be built (libseccomp's query of the
    kernel fails), which must be a refusal with a reason (SandboxUnavailable), not a crash of the worker."""
    code, report = self_check(worker_pod(), readable_copy, profile="no-seccomp")
    assert code == 1 and report["confined"] is False
    assert "seccomp filter cannot be built" in report["reason"]


# ---- what the worker's probe and the gateways' /ready make of it ----------------------------------------------


def healthcheck(redis: RedisServer, mode: str) -> subprocess.CompletedProcess[str]:
    """docker/healthcheck.py as the probe runs it, with the password in a file as the pod mounts it."""
    password_file = redis.directory / "probe-password"
    password_file.write_text(f"{redis.password}\n")
    env = {**os.environ, "REDIS_URL": redis.url, "PRECOND_REDIS_PASSWORD_FILE": str(password_file)}
    return subprocess.run([sys.executable, str(HEALTHCHECK), mode], env=env, capture_output=True, text=True,
                          timeout=30, check=False)


@pytest.fixture
def password_redis(tmp_path: Path) -> Iterator[RedisServer]:
    server = RedisServer(tmp_path, password="probe-password")
    server.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.mark.parametrize(("beat", "alive", "ready", "says"), [
    (None, False, False, "no heartbeat"),
    ({"sandbox": "unavailable", "sandbox_error": "the kernel policy could not be set up: X", "model_loaded": False},
     True, False, "cannot confine untrusted code here, so this worker takes no job: the kernel policy could not"),
    ({"sandbox": "confined", "model_loaded": False}, True, False, "the model is not loaded (still loading)"),
    ({"sandbox": "confined", "model_loaded": True}, True, True, ""),
    ({"sandbox": "confined", "model_loaded": False, "queues": ["precond:queue:check"]}, True, True, ""),
    ({"sandbox": "confined", "model_loaded": False, "queues": ["precond:queue:train"]}, True, True, ""),
])
def test_the_worker_probes_read_its_heartbeat(password_redis: RedisServer, beat: dict[str, Any] | None,
                                               alive: bool, ready: bool, says: str) -> None:
    if beat is not None:
        from precond.jobs.queue.keys import QUEUES

        body = {"id": "x", "host": os.uname().nodename, "pid": 1, "queues": list(QUEUES), **beat}
        password_redis.client().set(f"precond:worker:{os.uname().nodename}-1-abcdef", json.dumps(body))
    assert (healthcheck(password_redis, "worker").returncode == 0) is alive
    probe = healthcheck(password_redis, "worker-ready")
    assert (probe.returncode == 0) is ready
    assert says in probe.stdout


@pytest.fixture
def stack(tmp_path: Path, tiny_model_dir: Path) -> Stack:
    return make_stack(tmp_path, tiny_model_dir)


@root_only
def test_a_worker_in_a_pod_without_what_the_sandbox_needs_takes_no_job_and_says_why(stack: Stack) -> None:
    """The worker as root with every capability dropped: it stays alive (its liveness probe passes, so it is
    not restarted in a loop), its readiness probe fails naming the capabilities, and the gateways' /ready
    answers 503 with the same reason."""
    options = setpriv({**worker_pod(), "runAsUser": 0, "runAsGroup": 0})
    with serving(stack):
        stack._spawn("worker", ["setpriv", *options, sys.executable, "-m", "precond.worker.runner"])
        wait_until(lambda: stack.heartbeats(), 60, "the worker's heartbeat")
        (beat,) = stack.heartbeats()
        assert beat["sandbox"] == "unavailable" and "CAP_SETUID" in str(beat["sandbox_error"])
        ready = httpx.get(f"{stack.base_url}/ready", timeout=10)
        assert ready.status_code == 503 and "CAP_SETUID" in ready.text and "confine" in ready.text
        assert healthcheck(stack.redis, "worker").returncode == 0
        probe = healthcheck(stack.redis, "worker-ready")
        assert probe.returncode == 1 and "CAP_SETUID" in probe.stdout
