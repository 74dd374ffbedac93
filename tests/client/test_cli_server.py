"""`precond infer|next-action|check --server URL`: the request goes through the client to a running service
(a real keyed stack), as a user runs the command."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys

import pytest

from precond.stack.keyed import KeyedStack
from precond.stack.local import ROOT, check_body, infer_body
from precond_client import _core
from tests.cli.inprocess import precond as in_process


def precond(*args: str, stdin: str, api_key: str | None = None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PRECOND_API_KEY", "PRECOND_SERVER")}
    if api_key is not None:
        env["PRECOND_API_KEY"] = api_key
    return subprocess.run([sys.executable, "-m", "precond.cli", *args], input=stdin, capture_output=True, text=True,
                          timeout=300, cwd=ROOT, env=env, check=False)


def test_check_through_the_server_with_a_key_option(keyed: KeyedStack) -> None:
    body = check_body("system.INFORM('phone_number')", "system.GOODBYE()")
    done = precond("check", "-", "--server", keyed.url, "--api-key", keyed.keys["cli"], stdin=json.dumps(body))
    assert done.returncode == 0, done.stderr
    verdicts = json.loads(done.stdout)["results"]
    assert [v["call"] for v in verdicts] == body["calls"]
    assert not verdicts[0]["allowed"] and verdicts[1]["allowed"]


def test_infer_through_the_server_with_the_key_from_the_environment(keyed: KeyedStack) -> None:
    done = precond("infer", "-", "--server", keyed.url, stdin=json.dumps(infer_body(seed=303)),
                   api_key=keyed.keys["cli"])
    assert done.returncode == 0, done.stderr
    answer = json.loads(done.stdout)
    assert "self.user.requested_slot[slot]" in answer["preconditions"]["SYSTEM.INFORM"]
    assert "assert self.user.no_more" in answer["program"]


def test_server_errors_exit_2_naming_the_field_or_the_key(keyed: KeyedStack) -> None:
    body = infer_body(seed=304)
    body["demonstrations"][0] += "system.DANCE()\n"
    bad = precond("infer", "-", "--server", keyed.url, stdin=json.dumps(body), api_key=keyed.keys["cli"])
    assert bad.returncode == 2 and bad.stdout == ""
    assert "demonstrations[0]" in bad.stderr and "DANCE" in bad.stderr and "Traceback" not in bad.stderr
    unknown = precond("next-action", "-", "--server", keyed.url, "--api-key", "pk_wrong",
                      stdin=json.dumps({"spec": body["spec"], "history": "user = USER()\n"}))
    assert unknown.returncode == 2 and "unauthorized" in unknown.stderr and "unknown API key" in unknown.stderr


def test_an_unreachable_server_exits_4(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every try refused: the client's retries (their delays shortened, their count kept) end in exit 4."""
    from precond.stack.local import free_port

    monkeypatch.setattr(_core, "Retry", functools.partial(_core.Retry, base_s=0.01, max_s=0.05))
    monkeypatch.delenv("PRECOND_SERVER", raising=False)
    monkeypatch.setenv("PRECOND_API_KEY", "pk_x")
    done = in_process("check", "-", "--server", f"http://127.0.0.1:{free_port()}", stdin=json.dumps(check_body()))
    assert done.returncode == 4 and "cannot reach" in done.stderr
