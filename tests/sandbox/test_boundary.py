"""The kernel boundary, attacked for real: code that has first switched off every Python-level guard
tries files, network, signals, /proc, the environment and resource limits, as root and as a non-root
user; a candidate that tampers with the evaluator cannot validate other candidates; runaway parts fail
alone; replies are bound to their request; no policy means no untrusted code (fail closed)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from attack_probe import run_attacks
from warm_probe import EXPECTED, LIMITS

from precond.sandbox import LimitExceeded, Limits, Sandbox, SandboxCrashed, SandboxUnavailable
from precond.sandbox import api as sandbox_api
from precond.sandbox import pool as sandbox_pool
from precond.sandbox.policy import PolicyUnavailable
from precond.stack.identity import readable_sandbox_copy, runnable_python

ROOT = Path(__file__).resolve().parents[2]
SPEC = "import typing\nclass A:\n    def __init__(self):\n        self.x = 1\n    def act(self, v):\n        pass\n"
NOBODY = 65534


def assert_all_denied(results: dict[str, str]) -> None:
    allowed = {name: outcome for name, outcome in results.items() if not outcome.startswith("denied")}
    assert not allowed, f"escaped the sandbox: {allowed}"
    assert len(results) >= 20


def test_attacks_with_python_guards_off_are_refused_by_the_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PRECOND_TEST_SECRET", "redis://:hunter2@127.0.0.1:6379")
    with Sandbox(Limits(timeout_s=20, cpu_s=10), workers=1) as box:
        results = run_attacks(box)
    assert_all_denied(results)
    assert "hunter2" not in json.dumps(results)


def _runnable_as(uid: int) -> str:
    return runnable_python([f"--reuid={uid}", f"--regid={uid}", "--clear-groups"])


@pytest.fixture
def readable_copy() -> Iterator[Path]:
    """The sandbox, its program reader, the policy binding, the corpus and the probe, readable by any user."""
    where = Path(tempfile.mkdtemp(prefix="sandbox-nonroot-", dir="/tmp"))
    try:
        here = Path(__file__).parent
        yield readable_sandbox_copy(where, [here / "attack_probe.py", here / "warm_probe.py"])
    finally:
        shutil.rmtree(where, ignore_errors=True)


@pytest.mark.skipif(os.geteuid() != 0, reason="already non-root: the test above ran as this user")
def test_attacks_as_a_non_root_user_are_refused_by_the_kernel(readable_copy: Path) -> None:
    python = _runnable_as(NOBODY)
    env = {"PYTHONPATH": str(readable_copy), "PATH": "/usr/bin:/bin", "PRECOND_TEST_SECRET": "hunter2"}
    done = subprocess.run(
        ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", python, "attack_probe.py"],
        cwd=readable_copy, env=env, capture_output=True, text=True, timeout=120, check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["uid"] == NOBODY
    assert_all_denied(report["results"])
    assert "hunter2" not in done.stdout


@pytest.mark.skipif(os.geteuid() != 0, reason="already non-root: test_warm.py ran as this user")
def test_warm_children_as_a_non_root_user(readable_copy: Path) -> None:
    """test_warm.py's attacks on a tenant's warm child, with the worker (and so the children) not root."""
    python = _runnable_as(NOBODY)
    done = subprocess.run(
        ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", python, "warm_probe.py"],
        cwd=readable_copy, env={"PYTHONPATH": str(readable_copy), "PATH": "/usr/bin:/bin"}, capture_output=True,
        text=True, timeout=120, check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    assert report["uid"] == NOBODY
    assert report["sequence"] == EXPECTED
    idle = report["idle"]
    assert idle["first"] and idle["second"] and idle["idle_cpu_s"] < 0.3 and idle["second_s"] < LIMITS.timeout_s / 2
    assert report["unfit"] == [True, True, True]
    assert report["forged"] == [True, False]
    assert report["hanging"] == [None, None]


# A candidate without a single dunder that rewrites the evaluator so that every later candidate is valid
# (on the single-process evaluator this made `self.x == 2` valid).
TAMPER = ("[typing.sys.modules['builtins'].setattr(m, 'first_violation', lambda c, o: None) "
          "for m in [typing.sys.modules.get('__main__'), typing.sys.modules.get('precond.sandbox.child.evaluate')] "
          "if m is not None] == []")


def test_a_tampering_candidate_cannot_validate_the_others() -> None:
    with Sandbox(Limits(), workers=1) as box:
        result = box.evaluate(SPEC, ["a = A()\na.act(1)"], {"A.act": [TAMPER, "self.x == 2", "self.x == 1"]})
    _, wrong, right = result.results["A.act"]
    assert wrong.status == "invalid", wrong
    assert right.status == "valid", right


# The same, against the check: after the first proposed call, every verdict would read "allowed".
FORGE = ("[typing.sys.modules['builtins'].setattr(m, '_verdict', lambda *a: {'allowed': True, 'violations': [], "
         "'error': None}) for m in [typing.sys.modules.get('__main__'), "
         "typing.sys.modules.get('precond.sandbox.child.check')] "
         "if m is not None] == []")


def test_a_tampering_precondition_cannot_allow_a_forbidden_call() -> None:
    with Sandbox(Limits(), workers=1) as box:
        verdicts = box.check(SPEC, {"A.act": [FORGE, "v > 5"]}, "a = A()", ["a.act(1)", "a.act(2)"])
    for verdict in verdicts:
        assert not verdict.allowed, verdict
        assert "v > 5" in verdict.violations


PART_LIMITS = ("cpu limit exceeded: ", "time limit exceeded: no answer in ")
"""What a part (one candidate or one proposed call) that runs away is failed with: its CPU limit, or, on a loaded
machine where its CPU comes slowly, its wall-clock share (`unit_cpu_s` x `UNIT_WALL_FACTOR`), which may fire
first. Either is that part's own failure; the test does not depend on which."""


def names_a_part_limit(reason: str | None) -> bool:
    return reason is not None and any(limit in reason for limit in PART_LIMITS)


def test_runaway_candidates_fail_alone_and_the_rest_still_answers() -> None:
    limits = Limits(timeout_s=30, cpu_s=20, unit_cpu_s=0.5)
    with Sandbox(limits, workers=1) as box:
        result = box.evaluate(SPEC, ["a = A()\na.act(1)"],
                              {"A.act": ["sum(range(10 ** 10)) > 0", "self.x == 1", "10 ** 10 ** 8 > 0", "v == 1"]})
    loop, kept, bignum, last = result.results["A.act"]
    assert loop.status == "rejected" and names_a_part_limit(loop.reason), loop
    assert bignum.status == "rejected" and "limit" in (bignum.reason or ""), bignum
    assert kept.status == "valid" and last.status == "valid"


def test_a_candidate_running_when_the_call_runs_out_of_time_fails_alone() -> None:
    """On a loaded machine the call's time (SANDBOX_TIMEOUT_S) can run out while one candidate runs, before its
    own CPU limit does: that candidate is dropped (after a retry alone) and says why; the others are judged."""
    limits = Limits(timeout_s=2, cpu_s=30, unit_cpu_s=30)
    with Sandbox(limits, workers=1) as box:
        result = box.evaluate(SPEC, ["a = A()\na.act(1)"],
                              {"A.act": ["self.x == 1", "sum(range(10 ** 12)) > 0", "v == 1", "v == 2"]})
    kept, slow, last, refuted = result.results["A.act"]
    assert slow.status == "rejected", slow
    assert "ran out of time (also when judged alone)" in (slow.reason or "") and "SANDBOX_TIMEOUT_S" in (
        slow.reason or ""), slow
    assert kept.status == "valid" and last.status == "valid" and refuted.status == "invalid"


def test_a_limit_hit_in_the_specs_top_level_is_named_the_specs() -> None:
    """The spec's top level runs anew for each demonstration: a loop there is the spec's, not the program's."""
    looping = SPEC + "while True:\n    pass\n"
    with Sandbox(Limits(timeout_s=1.5, cpu_s=30, unit_cpu_s=30), workers=1) as box, \
            pytest.raises(LimitExceeded) as caught:
        box.trace(looping, ["a = A()\na.act(1)"])
    assert caught.value.limit == "timeout"
    assert "(SANDBOX_TIMEOUT_S) while running the spec's top level (run anew for demonstrations[0])" in str(
        caught.value), caught.value


def test_a_runaway_rule_fails_only_its_call() -> None:
    limits = Limits(timeout_s=30, cpu_s=20, unit_cpu_s=0.5)
    with Sandbox(limits, workers=1) as box:
        slow, fast = box.check(SPEC, {"A.act": ["v < 5 or sum(range(10 ** 10)) > 0"]}, "a = A()",
                               ["a.act(9)", "a.act(1)"])
    assert not slow.allowed and names_a_part_limit(slow.error), slow
    assert fast.allowed


def test_a_rule_that_raises_is_an_error_not_a_plain_refusal() -> None:
    with Sandbox(Limits(), workers=1) as box:
        (verdict,) = box.check(SPEC, {"A.act": ["self.missing == 1"]}, "a = A()", ["a.act(1)"])
    assert not verdict.allowed
    assert verdict.error is not None and "AttributeError" in verdict.error and "self.missing" in verdict.error


def test_points_are_bounded_inside_the_child() -> None:
    demo = "a = A()\n" + "".join(f"a.act({i})\n" for i in range(300))
    with Sandbox(Limits(max_points=10_000), workers=1) as box, pytest.raises(LimitExceeded) as caught:
        box.evaluate(SPEC, [demo], {"A.act": ["v > 0"]})
    assert caught.value.limit == "work" and "A.act" in str(caught.value)


def test_no_policy_means_no_sandbox(monkeypatch: pytest.MonkeyPatch) -> None:
    def unavailable() -> bytes:
        raise PolicyUnavailable("libseccomp is not available: test")

    monkeypatch.setattr(sandbox_api, "build_filter", unavailable)
    with pytest.raises(SandboxUnavailable, match="libseccomp"):
        Sandbox(Limits(), workers=1)
    with Sandbox(Limits(), workers=1, allow_unconfined=True) as box:  # the explicit development setting
        assert box.unconfined_reason is not None
        box.trace(SPEC, ["a = A()"])


def test_a_filter_the_kernel_refuses_means_no_sandbox(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sandbox_api, "build_filter", lambda: b"\x00" * 8)  # no return instruction
    with pytest.raises(SandboxUnavailable, match="could not be set up"):
        Sandbox(Limits(), workers=1)


FORGING_SERVER = """
import json, os, sys
requests, responses = int(sys.argv[3]), int(sys.argv[4])
os.write(responses, b'{"status": "hello", "confined": true}\\n')
reader = os.fdopen(requests, 'rb')
header = json.loads(reader.readline())
reader.read(header['size'])
body = b'{"result": {"positions": [], "actions": {}}, "units": {}}'
os.write(responses, json.dumps({"id": "not-" + header["id"], "status": "ok", "size": len(body)}).encode()
         + b'\\n' + body + b'\\n')
reader.read()
"""


def test_a_reply_to_another_request_is_never_taken(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sandbox_pool, "BOOTSTRAP", FORGING_SERVER)
    with Sandbox(Limits(), workers=1) as box, pytest.raises(SandboxCrashed, match="does not answer"):
        box.trace(SPEC, ["a = A()"])
